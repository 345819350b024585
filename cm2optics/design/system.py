"""The CM² system: its parts, the cross-part checks that make them one printable, imaging device,
and the heights of the imaging elements in the device frame.

Device frame (CAD, ray tracing): origin at the centre of the sensor's photosensitive
surface, ``+z`` along the optical axis from the sensor towards the sample, ``x`` along the
sensor rows (width), ``y`` along its columns. A height ``z_*_mm`` is measured in this frame.
Derived first-order optics (focal length, the plane of best focus, magnification, object pixel,
working distance, NA) are functions of a design in :mod:`cm2optics.optics.first_order`.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import yaml

from cm2optics.design import paraxial
from cm2optics.design.as_built import AsBuilt
from cm2optics.design.as_built_illumination import IlluminationAsBuilt
from cm2optics.design.coerce import dataclass_from_dict, to_plain, write_text_atomic
from cm2optics.design.filters import AbsorptionFilter, InterferenceFilter
from cm2optics.design.illumination import LED, Collimator, LEDArray
from cm2optics.design.imaging import ImagedVolume, ImagingLayout
from cm2optics.design.mechanics import BasePlate, LEDHousing, Mechanics, MLAHousing
from cm2optics.design.mla import ApertureMask, MicrolensArray
from cm2optics.design.sensor import Sensor, SensorBoard
from cm2optics.design.validation import DesignError, check

__all__ = ["SystemDesign"]


@dataclass(frozen=True)
class SystemDesign:
    """One CM² device. ``absorption_filter`` and ``collimator`` may be ``None`` (a V1 device).

    ``as_built`` (optional in YAML): how the assembled device departs from the design
    (:class:`~cm2optics.design.as_built.AsBuilt`); absent or all-default, it leaves the design's
    YAML and parameter hash as they were. ``illumination_as_built`` (optional): the same for
    the LED units (:class:`~cm2optics.design.as_built_illumination.IlluminationAsBuilt`).
    """

    name: str
    sensor: Sensor
    sensor_board: SensorBoard
    mla: MicrolensArray
    aperture_mask: ApertureMask
    emission_filter: InterferenceFilter
    absorption_filter: AbsorptionFilter | None
    imaging: ImagingLayout
    volume: ImagedVolume
    led: LED
    led_array: LEDArray
    collimator: Collimator | None
    excitation_filter: InterferenceFilter
    mechanics: Mechanics
    mla_housing: MLAHousing
    led_housing: LEDHousing
    base_plate: BasePlate
    as_built: AsBuilt = field(default_factory=AsBuilt)
    illumination_as_built: IlluminationAsBuilt = field(default_factory=IlluminationAsBuilt)

    def __post_init__(self) -> None:
        self._check_as_built()
        self._check_mla_on_sensor()
        self._check_filter_bands()
        self._check_film()
        self._check_mla_housing()
        self._check_led_housing()
        check(
            "imaging.mla_to_sensor_mm",
            self.imaging.mla_to_sensor_mm,
            paraxial.has_real_image(self),
            "the sensor must lie beyond the lenslets' back focus (no real image of the sample otherwise)",
        )

    def _check_as_built(self) -> None:
        """Per-lenslet lists have one entry per full lenslet, per-unit lists one per LED unit (or none)."""
        lenslets = self.mla.rows * self.mla.cols
        per_item = (
            (
                self.as_built,
                "as_built",
                ("lenslet_decenter_mm", "lenslet_transmission"),
                lenslets,
                f"lenslet ({lenslets} = mla.rows × mla.cols, row by row)",
            ),
            (
                self.illumination_as_built,
                "illumination_as_built",
                ("led_flux", "led_tilt_deg", "collimator_decenter_mm"),
                self.led_array.count,
                f"LED unit ({self.led_array.count} = led_array.count)",
            ),
        )
        for section, prefix, names, count, what in per_item:
            for name in names:
                value = getattr(section, name)
                check(
                    f"{prefix}.{name}",
                    [list(v) if isinstance(v, tuple) else v for v in value],
                    len(value) in (0, count),
                    f"must list one value per {what} or be empty",
                )

    def _check_mla_on_sensor(self) -> None:
        """The MLA fits the sensor's active area."""
        mla, sensor = self.mla, self.sensor
        check(
            "mla.pitch_mm",
            mla.pitch_mm,
            mla.width_mm <= sensor.active_width_mm and mla.length_mm <= sensor.active_length_mm,
            f"the MLA ({mla.width_mm:.3f} × {mla.length_mm:.3f} mm) must fit the sensor's active area "
            f"({sensor.active_width_mm:.3f} × {sensor.active_length_mm:.3f} mm)",
        )

    def _check_filter_bands(self) -> None:
        """The emission passband lies above the excitation band; the film cuts on below its top (nm)."""
        emission, excitation = self.emission_filter, self.excitation_filter
        emission_low = emission.center_nm - emission.bandwidth_nm / 2
        emission_high = emission.center_nm + emission.bandwidth_nm / 2
        check(
            "emission_filter.center_nm",
            emission.center_nm,
            emission_low >= excitation.center_nm + excitation.bandwidth_nm / 2,
            f"the emission passband ({emission_low:g}–{emission_high:g} nm) must lie above the excitation "
            f"filter's ({excitation.center_nm:g} ± {excitation.bandwidth_nm / 2:g} nm): fluorescence is red-shifted",
        )
        if self.absorption_filter is not None:
            check(
                "absorption_filter.cut_on_nm",
                self.absorption_filter.cut_on_nm,
                self.absorption_filter.cut_on_nm < emission_high,
                f"the film must cut on below the top of the emission passband ({emission_high:g} nm), "
                "or it absorbs all the signal",
            )

    def _check_film(self) -> None:
        """The absorption film lies below the MLA and exceeds it enough to pass it through its ledge (mm)."""
        mla, lay, mech = self.mla, self.imaging, self.mechanics
        if self.absorption_filter is not None:
            film_top = lay.film_to_sensor_mm + self.absorption_filter.thickness_mm
            check(
                "imaging.film_to_sensor_mm",
                lay.film_to_sensor_mm,
                film_top < lay.mla_to_sensor_mm,
                f"the film (top at {film_top:.3f} mm) must lie below the MLA's flat face at {lay.mla_to_sensor_mm} mm",
            )
        if self.absorption_filter is not None:
            film = self.absorption_filter
            spacer = min(film.width_mm - mla.width_mm, film.length_mm - mla.length_mm) - 2 * self.mla_housing.lip_mm
            check(
                "absorption_filter.width_mm",
                film.width_mm,
                spacer >= 2 * mech.clearance_mm - 1e-9,
                "the MLA goes into the housing from the sensor side, through the film's ledge: the film must "
                f"exceed the MLA by 2 × (mla_housing.lip_mm + mechanics.clearance_mm) = "
                f"{2 * (self.mla_housing.lip_mm + mech.clearance_mm):.2f} mm along x and y",
            )

    def _check_mla_housing(self) -> None:
        """The MLA housing is printable: corner tabs, mask opening, tower seat and walls, screw holes (mm)."""
        mla, lay, mech = self.mla, self.imaging, self.mechanics
        # The corner tabs that hold the MLA from above reach lip_mm over its corners: they span the
        # mask gap plus the depth below the vertices of the lens under the tab's inner edge, at its
        # point nearest a (full) corner lenslet's vertex, or of the land outside the aperture.
        offset = max(mla.pitch_mm / 2 - self.mla_housing.lip_mm / 2, 0.0)
        depth = float(mla.sag_mm(offset * math.sqrt(2.0))) if offset <= mla.aperture_mm / 2 else mla.corner_sag_mm
        tab = lay.mask_gap_mm + depth
        check(
            "imaging.mask_gap_mm",
            lay.mask_gap_mm,
            tab >= mech.min_wall_mm - 1e-9,
            f"the corner tabs that hold the MLA from above would be {tab:.3f} mm thick "
            f"(< mechanics.min_wall_mm = {mech.min_wall_mm}: not printable); widen the mask gap",
        )
        check(
            "aperture_mask.opening_mm",
            self.aperture_mask.opening_mm,
            self.aperture_mask.opening_mm <= min(mla.width_mm, mla.length_mm) + 1e-9,
            f"the opening cannot exceed the MLA ({mla.width_mm:.3f} × {mla.length_mm:.3f} mm)",
        )
        seat = max(self.emission_filter.width_mm, self.emission_filter.length_mm, self.aperture_mask.outer_mm)
        check(
            "mla_housing.outer_mm",
            self.mla_housing.outer_mm,
            self.mla_housing.outer_mm >= seat + 2 * (mech.clearance_mm + mech.wall_mm),
            f"the tower must hold a {seat} mm seat with walls: ≥ {seat + 2 * (mech.clearance_mm + mech.wall_mm):.2f} mm",
        )
        top_wall = (self.mla_housing.outer_mm - seat) / 2 - mech.clearance_mm - self.mla_housing.chamfer_mm
        check(
            "mla_housing.chamfer_mm",
            self.mla_housing.chamfer_mm,
            top_wall >= mech.min_wall_mm - 1e-9,
            f"the chamfer leaves a {top_wall:.3f}-mm wall at the tower top (< min_wall_mm = {mech.min_wall_mm})",
        )
        check(
            "mla_housing.outer_mm",
            self.mla_housing.outer_mm,
            self.mla_housing.outer_mm
            < self.sensor_board.hole_spacing_mm - self.sensor_board.hole_diameter_mm - 2 * mech.wall_mm,
            "the tower must leave room for the board's screw holes",
        )

    def _check_led_housing(self) -> None:
        """The collimator, excitation filter and LED package fit the LED housing; the filter rests on the collimator (mm)."""
        mech = self.mechanics
        if self.collimator is not None:
            pocket = self.collimator.footprint_mm + 2 * (mech.clearance_mm + mech.min_wall_mm)
            check(
                "collimator.footprint_mm",
                self.collimator.footprint_mm,
                pocket <= self.led_housing.outer_mm,
                f"a collimator wider than its housing: footprint + clearance + walls = {pocket:.2f} mm "
                f"> led_housing.outer_mm = {self.led_housing.outer_mm}",
            )
            exit_z = self.collimator.led_gap_mm + self.collimator.height_mm
            check(
                "led_array.excitation_gap_mm",
                self.led_array.excitation_gap_mm,
                abs(self.led_array.excitation_gap_mm - exit_z) <= 1e-6,
                f"must equal collimator.led_gap_mm + height_mm = {exit_z:g}: the excitation filter rests on the "
                "collimator's exit face (a printed spacer in a smaller gap would be thinner than a printable wall)",
            )
        seated = (
            (
                "excitation_filter.width_mm",
                self.excitation_filter.width_mm,
                self.excitation_filter.length_mm,
                "excitation filter",
            ),
            ("led.package_width_mm", self.led.package_width_mm, self.led.package_length_mm, "LED package"),
        )
        for field_path, width, length, part in seated:
            size = max(width, length)
            check(
                field_path,
                size,
                size + 2 * (mech.clearance_mm + mech.min_wall_mm) <= self.led_housing.outer_mm,
                f"the {part} must fit its housing (led_housing.outer_mm = {self.led_housing.outer_mm})",
            )

    # -- heights in the device frame (mm) -------------------------------------------------
    @property
    def mla_vertex_z_mm(self) -> float:
        return self.imaging.mla_to_sensor_mm + self.mla.thickness_mm

    @property
    def mask_z_mm(self) -> float:
        """Lower face of the aperture mask."""
        return self.mla_vertex_z_mm + self.imaging.mask_gap_mm

    @property
    def emission_filter_z_mm(self) -> float:
        """Lower face of the emission filter."""
        return self.mask_z_mm + self.aperture_mask.thickness_mm + self.imaging.filter_gap_mm

    # -- files ------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain data of the design; ``as_built`` holds only its non-default fields and is left
        out when the device is built as designed (so the parameter hash is the design's)."""
        data = to_plain(self)
        if data["led_array"]["aim_mm"] == 0.0:  # the default aim (the field's centre) keeps old files and hashes
            del data["led_array"]["aim_mm"]
        if self.collimator is not None and not self.collimator.is_freeform:
            del data["collimator"]["lens_freeform_um"]  # a revolved lens keeps old files and hashes
        if self.collimator is not None and self.collimator.tir_max_radius_mm == 0.0:
            del data["collimator"]["tir_max_radius_mm"]  # the whole TIR wall keeps old files and hashes
        if self.collimator is not None and self.collimator.tir_cone_deg == 0.0:
            del data["collimator"]["tir_cone_deg"]  # so does the designed wall
            del data["collimator"]["tir_cone_curvature_per_mm"]
        if self.collimator is not None and not self.collimator.tir_is_freeform:
            del data["collimator"]["tir_cos2"]  # a revolved wall keeps old files and hashes
            del data["collimator"]["tir_cos4"]
        changed = self.as_built.changed()
        if changed:
            data["as_built"] = changed
        else:
            del data["as_built"]
        changed = self.illumination_as_built.changed()
        if changed:
            data["illumination_as_built"] = changed
        else:
            del data["illumination_as_built"]
        return data

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, allow_unicode=True)

    def save(self, path: str | Path) -> None:
        """Write the design as YAML (atomically)."""
        write_text_atomic(Path(path), self.to_yaml())

    def parameter_hash(self) -> str:
        """Short SHA-256 of the canonical design, for manifests and caches."""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def with_changes(self, changes: dict[str, Any]) -> SystemDesign:
        """A copy with dotted-path fields replaced (``{"mla.radius_mm": 1.7}``,
        ``{"as_built.mla_rotation_deg": 0.5}``), validated anew."""
        data = to_plain(self)
        for path, value in changes.items():
            node = data
            *parents, leaf = path.split(".")
            for part in parents:
                if not isinstance(node.get(part), dict):
                    raise DesignError(path, value, "no such field in the design")
                node = node[part]
            if leaf not in node:
                raise DesignError(path, value, "no such field in the design")
            node[leaf] = value.value if isinstance(value, Enum) else value
        return dataclass_from_dict(SystemDesign, data, "")


# ----------------------------------------------------------------------------- YAML edge
