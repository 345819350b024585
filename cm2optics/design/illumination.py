"""The excitation side: LED, TIR collimator and the ring of LED units."""

from __future__ import annotations

from dataclasses import dataclass

from cm2optics.design.materials import Material
from cm2optics.design.validation import check, in_range, non_negative, positive

__all__ = ["Collimator", "LED", "LEDArray"]


@dataclass(frozen=True)
class LED:
    """Surface-mount LED.

    emitter_mm: side of the square emitting area, mm.
    package_width_mm, package_length_mm: package footprint, mm.
    package_height_mm: board to emitting surface, mm.
    peak_nm: peak emission wavelength, nm.
    radiant_flux_mw: radiant flux at the drive current, mW.
    """

    emitter_mm: float
    package_width_mm: float
    package_length_mm: float
    package_height_mm: float
    peak_nm: float
    radiant_flux_mw: float

    def __post_init__(self) -> None:
        positive(self, "emitter_mm", "package_width_mm", "package_length_mm", "package_height_mm", "radiant_flux_mw")
        in_range(self, "peak_nm", 350.0, 1000.0, " nm")
        check(
            "emitter_mm",
            self.emitter_mm,
            self.emitter_mm <= min(self.package_width_mm, self.package_length_mm),
            "the emitter must fit on its package",
        )


@dataclass(frozen=True)
class Collimator:
    """Rotationally symmetric freeform TIR collimator in front of each LED, its focus on the
    LED's centre; :mod:`cm2optics.optics.collimator` computes its profile from these numbers.

    material: printed transparent material.
    led_gap_mm: LED emitting surface to the collimator's entry plane (the cavity mouth), mm.
    lens_half_angle_deg: half-angle of the cone collimated by the inner refractive lens (a
        hyperbola on the cavity floor); rays beyond it cross the cavity wall and are
        collimated by the outer TIR surface, degrees.
    cavity_radius_mm: radius of the cylindrical entry cavity around the LED, mm.
    entry_wall_mm: radial wall between the cavity and the outer TIR surface at the entry
        plane, where the TIR surface starts, mm.
    footprint_mm: side of the square exit flange, mm.
    height_mm: entry plane to exit face, mm.
    flange_mm: thickness of the square exit flange, mm.
    lens_spread_deg: output half-angle (in air) of the lens sub-beam's edge ray, degrees;
        0 collimates it, more spreads it into a flat-top cone (:mod:`cm2optics.optics.collimator_shaping`).
    tir_spread_deg: output half-angle of the TIR sub-beam's edge ray, degrees (0: collimated).
    tir_crossing: the TIR sub-beam crosses the axis rather than spreading outwards.
    lens_exponent, tir_exponent: exponent γ of each sub-beam's ray mapping tan ψ ∝ F^γ (F the
        sub-beam's flux fraction): 0.5 lights a disc uniformly, smaller pushes power outwards.
    lens_freeform_um: Zernike coefficients c_1, c_2, … (Noll's order and unit-RMS
        normalisation, over the cavity radius) of a sag added to the lens, µm: the lens departs
        from revolution (:mod:`cm2optics.optics.freeform`); empty (the default, left out of the
        YAML) or all zero: the revolved part.
    tir_max_radius_mm: radius at which the TIR wall stops, mm (the authors' architecture: their
        wall ends at r ≈ 1.9 mm): the rays meant for the wall above it are not collimated, they
        cross the side and flange unreflected; 0 (the default, left out of the YAML): the whole
        wall, which must then fit inside the footprint.
    tir_cone_deg, tir_cone_curvature_per_mm: a TIR wall of prescribed shape instead of the
        designed one (0°, the default, left out of the YAML: the wall designed for the LED's
        centre): ``r(z) = a + entry_wall_mm + tan(β) (z − g) + κ (z − g)² / 2`` from the entry
        plane (β the cone's half-angle, degrees; κ its change of slope, 1/mm) up to
        ``tir_max_radius_mm`` or the flange. The designed wall collimates a point source but
        needs r ≈ 2.3–3.3 mm once the cavity encloses the 1-mm emitter; a cone of ≈ 30° inside
        the 4-mm footprint is what the authors' part does. The lens's rays keep their design.
    tir_cos2, tir_cos4: the TIR wall departs from revolution (dimensionless, each within ±0.4,
        ``|tir_cos2| + |tir_cos4| ≤ 0.5``): at azimuth φ of the LED frame (from its x axis, which
        lies across the unit's plane of tilt; y lies in it) the wall's radial departure from its
        entry ring is scaled, ``r(z, φ) = r_e + (r(z) − r_e)(1 + tir_cos2 cos 2φ + tir_cos4 cos 4φ)``
        (``r_e = cavity_radius_mm + entry_wall_mm``, ``r(z)`` the revolved wall, designed or
        prescribed, and its step up to the flange). A scale above 1 makes the wall flatter there
        (it spreads its rays less), below 1 steeper. The scale stays ≥ 0.5, so the wall still
        widens upwards at every φ (no overhang); it must fit the square footprint at every φ
        (:func:`cm2optics.optics.collimator.tir_wall_reach_mm`). 0 and 0 (the default, left out
        of the YAML): the revolved wall. :mod:`cm2optics.optics.freeform`.
    """

    material: Material
    led_gap_mm: float
    lens_half_angle_deg: float
    cavity_radius_mm: float
    entry_wall_mm: float
    footprint_mm: float
    height_mm: float
    flange_mm: float
    lens_spread_deg: float
    tir_spread_deg: float
    tir_crossing: bool
    lens_exponent: float
    tir_exponent: float
    lens_freeform_um: tuple[float, ...] = ()
    tir_max_radius_mm: float = 0.0
    tir_cone_deg: float = 0.0
    tir_cone_curvature_per_mm: float = 0.0
    tir_cos2: float = 0.0
    tir_cos4: float = 0.0

    @property
    def is_freeform(self) -> bool:
        """Whether the lens departs from revolution (a non-zero Zernike coefficient)."""
        return any(c != 0.0 for c in self.lens_freeform_um)

    @property
    def tir_is_freeform(self) -> bool:
        """Whether the TIR wall departs from revolution (``tir_cos2`` or ``tir_cos4`` non-zero)."""
        return self.tir_cos2 != 0.0 or self.tir_cos4 != 0.0

    @property
    def collimates(self) -> bool:
        """Whether both sub-beams are designed parallel to the axis (no beam shaping)."""
        return self.lens_spread_deg == 0.0 and self.tir_spread_deg == 0.0

    def __post_init__(self) -> None:
        check("material", self.material, self.material.is_transparent, "a collimator must be transparent")
        non_negative(self, "led_gap_mm")
        in_range(self, "lens_half_angle_deg", 5.0, 60.0, "°")
        positive(self, "cavity_radius_mm", "entry_wall_mm", "footprint_mm", "height_mm", "flange_mm")
        check("flange_mm", self.flange_mm, self.flange_mm < self.height_mm, f"must be < height_mm = {self.height_mm}")
        check(
            "entry_wall_mm",
            self.entry_wall_mm,
            self.cavity_radius_mm + self.entry_wall_mm < self.footprint_mm / 2,
            f"the cavity and its wall must fit inside footprint_mm/2 = {self.footprint_mm / 2} "
            f"(cavity_radius_mm + entry_wall_mm = {self.cavity_radius_mm + self.entry_wall_mm})",
        )
        in_range(self, "lens_spread_deg", 0.0, 40.0, "°")
        in_range(self, "tir_spread_deg", 0.0, 40.0, "°")
        in_range(self, "lens_exponent", 0.1, 1.0)
        in_range(self, "tir_exponent", 0.1, 1.0)
        check(
            "lens_freeform_um",
            list(self.lens_freeform_um),
            len(self.lens_freeform_um) <= 28 and all(abs(c) <= 200.0 for c in self.lens_freeform_um),
            "at most 28 Zernike coefficients (Noll j = 1–28), each within ±200 µm",
        )
        non_negative(self, "tir_max_radius_mm")
        check(
            "tir_max_radius_mm",
            self.tir_max_radius_mm,
            self.tir_max_radius_mm == 0.0
            or self.cavity_radius_mm + self.entry_wall_mm < self.tir_max_radius_mm < self.footprint_mm / 2,
            f"0 (the whole wall) or between cavity_radius_mm + entry_wall_mm = "
            f"{self.cavity_radius_mm + self.entry_wall_mm} and footprint_mm/2 = {self.footprint_mm / 2}",
        )
        check(
            "tir_cone_deg",
            self.tir_cone_deg,
            self.tir_cone_deg == 0.0 or (5.0 <= self.tir_cone_deg <= 60.0 and self.tir_spread_deg == 0.0),
            "0 (the designed wall) or 5–60° with tir_spread_deg = 0 (a cone has no ray mapping to shape)",
        )
        check(
            "tir_cone_curvature_per_mm",
            self.tir_cone_curvature_per_mm,
            self.tir_cone_deg != 0.0 or self.tir_cone_curvature_per_mm == 0.0,
            "needs tir_cone_deg > 0",
        )
        in_range(self, "tir_cos2", -0.4, 0.4)
        in_range(self, "tir_cos4", -0.4, 0.4)
        check(
            "tir_cos2",
            self.tir_cos2,
            abs(self.tir_cos2) + abs(self.tir_cos4) <= 0.5,
            f"|tir_cos2| + |tir_cos4| must be ≤ 0.5 (tir_cos4 = {self.tir_cos4}): the wall must widen upwards at every azimuth",
        )


@dataclass(frozen=True)
class LEDArray:
    """Placement of the LED units around the imaging axis.

    count: number of units, evenly spaced in azimuth.
    offset_mm: radial distance from the optical axis of each unit's aperture (the centre of
        the excitation filter's lower face, where light leaves the unit), mm.
    tilt_deg: angle between each unit's axis and the optical axis, degrees; the axis is aimed
        at its aim point on the nominal focal plane, which fixes the unit's height.
    azimuth_deg: azimuth of the first unit from +x, degrees.
    excitation_gap_mm: LED emitting surface to the excitation filter's lower face, mm.
    aim_mm: where each unit's axis meets the nominal focal plane, as a signed distance from the
        optical axis along the unit's own radial direction, mm: 0 aims at the centre of the
        field (the default, left out of the YAML), < 0 past it, > 0 short of it. Must stay
        below ``offset_mm`` (the axis descends towards the field) when the unit is tilted, and
        be 0 for an untilted unit (its axis meets the plane under its aperture).
    """

    count: int
    offset_mm: float
    tilt_deg: float
    azimuth_deg: float
    excitation_gap_mm: float
    aim_mm: float = 0.0

    def __post_init__(self) -> None:
        check("count", self.count, 1 <= self.count <= 12, "must lie within 1–12")
        positive(self, "offset_mm", "excitation_gap_mm")
        in_range(self, "tilt_deg", 0.0, 80.0, "°")
        in_range(self, "azimuth_deg", -360.0, 360.0, "°")
        if self.tilt_deg > 0.0:
            check(
                "aim_mm",
                self.aim_mm,
                -self.offset_mm < self.aim_mm < self.offset_mm,
                f"a tilted unit's axis must meet the focal plane within ±offset_mm = ±{self.offset_mm} "
                "of the optical axis (it descends from the aperture towards and at most past the centre)",
            )
        else:
            check("aim_mm", self.aim_mm, self.aim_mm == 0.0, "must be 0 for an untilted unit (tilt_deg = 0)")


# ----------------------------------------------------------------------------- mechanics
