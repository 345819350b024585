"""The CM² system design: frozen, validated dataclasses, YAML load/dump, derived optics.

Every number that shapes a part, a ray or a pixel lives here, once. Lengths are in mm,
pixel pitches in µm, wavelengths in nm, angles in degrees (``_deg``) in files and radians
(``_rad``) in code.

Device frame (CAD, ray tracing): origin at the centre of the sensor's photosensitive
surface, ``+z`` along the optical axis from the sensor towards the sample, ``x`` along the
sensor rows (width), ``y`` along its columns. A height ``z_*_mm`` is measured in this frame.
Object-space coordinates of PSF scans and volumes instead measure ``z`` from the nominal
focal plane with ``+z`` towards the device (DESIGN.md); :meth:`SystemDesign.object_z_to_height_mm`
converts.

Construct parts directly (``MicrolensArray(...)``) or load a YAML preset
(:func:`load_preset`, :func:`load_design`); either way a bad value raises
:class:`DesignError` naming the field, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
import types
import typing
from dataclasses import dataclass, fields
from enum import Enum, StrEnum
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any, Union

import yaml

from cm2optics import paraxial
from cm2optics.materials import Material, refractive_index
from cm2optics.errors import UserError

__all__ = [
    "AbsorptionFilter",
    "ApertureMask",
    "BasePlate",
    "Collimator",
    "DesignError",
    "ImagedVolume",
    "ImagingLayout",
    "InterferenceFilter",
    "LED",
    "LEDArray",
    "LEDHousing",
    "MLAHousing",
    "Mechanics",
    "MicrolensArray",
    "Sensor",
    "SensorBoard",
    "Side",
    "SystemDesign",
    "available_presets",
    "load_design",
    "load_preset",
]


class DesignError(UserError):
    """A design value that is missing, misspelled, mistyped or physically impossible.

    ``field`` is the dotted path of the offending field (``mla.radius_mm``).
    """

    def __init__(self, field_path: str, value: Any, allowed: str):
        self.field = field_path
        self.value = value
        self.allowed = allowed
        super().__init__(f"{field_path} = {value!r}: {allowed}")


def _check(name: str, value: Any, ok: bool, allowed: str) -> None:
    if not ok:
        raise DesignError(name, value, allowed)


def _positive(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _check(name, value, math.isfinite(value) and value > 0, "must be a finite number > 0")


def _non_negative(obj: Any, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _check(name, value, math.isfinite(value) and value >= 0, "must be a finite number ≥ 0")


def _in_range(obj: Any, name: str, low: float, high: float, unit: str = "") -> None:
    value = getattr(obj, name)
    _check(name, value, math.isfinite(value) and low <= value <= high, f"must lie within {low}–{high}{unit}")


class Side(StrEnum):
    """A side of the lenslet array, named by the device-frame axis it faces."""

    PLUS_X = "+x"
    MINUS_X = "-x"
    PLUS_Y = "+y"
    MINUS_Y = "-y"


# ----------------------------------------------------------------------------- sensor


@dataclass(frozen=True)
class Sensor:
    """Image sensor: pixel grid and package.

    name: model name (informational).
    width_px, height_px: active pixels along x (rows) and y.
    pixel_um: pixel pitch, µm.
    bit_depth: ADC bits of a raw frame.
    package_width_mm, package_length_mm: package footprint along x and y, mm.
    package_height_mm: PCB top to the photosensitive surface, mm.
    """

    name: str
    width_px: int
    height_px: int
    pixel_um: float
    bit_depth: int
    package_width_mm: float
    package_length_mm: float
    package_height_mm: float

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            _check(name, getattr(self, name), 16 <= getattr(self, name) <= 100_000, "must lie within 16–100000 px")
        _in_range(self, "pixel_um", 0.5, 20.0, " µm")
        _check("bit_depth", self.bit_depth, self.bit_depth in (8, 10, 12, 14, 16), "must be one of 8, 10, 12, 14, 16")
        _positive(self, "package_width_mm", "package_length_mm", "package_height_mm")
        _check(
            "package_width_mm",
            self.package_width_mm,
            self.package_width_mm >= self.active_width_mm and self.package_length_mm >= self.active_length_mm,
            f"the package must enclose the active area {self.active_width_mm:.2f} × {self.active_length_mm:.2f} mm",
        )

    @property
    def active_width_mm(self) -> float:
        return self.width_px * self.pixel_um / 1000.0

    @property
    def active_length_mm(self) -> float:
        return self.height_px * self.pixel_um / 1000.0


@dataclass(frozen=True)
class SensorBoard:
    """The camera PCB the MLA housing screws onto.

    size_mm: side of the square board, mm.
    thickness_mm: PCB thickness, mm.
    hole_spacing_mm: centre-to-centre spacing of the four mounting holes (square pattern), mm.
    hole_diameter_mm: clearance hole diameter for the mounting screws, mm.
    """

    size_mm: float
    thickness_mm: float
    hole_spacing_mm: float
    hole_diameter_mm: float

    def __post_init__(self) -> None:
        _positive(self, "size_mm", "thickness_mm", "hole_spacing_mm", "hole_diameter_mm")
        _check(
            "hole_spacing_mm",
            self.hole_spacing_mm,
            self.hole_spacing_mm + self.hole_diameter_mm < self.size_mm,
            f"the holes must lie on the board (spacing + diameter < size_mm = {self.size_mm})",
        )


# ----------------------------------------------------------------------------- imaging optics


@dataclass(frozen=True)
class MicrolensArray:
    """Square-cell array of plano-convex spherical lenslets, curved side towards the sample.

    rows, cols: lenslets along y and x.
    pitch_mm: cell pitch, mm.
    radius_mm: radius of curvature of every lenslet, mm.
    aperture_mm: side of each lenslet's square aperture inside its cell, mm (= pitch_mm for
        a 100 % fill factor; smaller leaves a flat land between lenslets).
    thickness_mm: substrate plus lens: flat face to lens vertex, mm.
    material: lens material.
    partial_border_mm: width of partial lenslets left around the array by dicing, mm (0: none).
    partial_sides: the sides that carry partial lenslets.
    """

    rows: int
    cols: int
    pitch_mm: float
    radius_mm: float
    aperture_mm: float
    thickness_mm: float
    material: Material
    partial_border_mm: float
    partial_sides: tuple[Side, ...]

    def __post_init__(self) -> None:
        for name in ("rows", "cols"):
            _check(name, getattr(self, name), 1 <= getattr(self, name) <= 15, "must lie within 1–15")
        _positive(self, "pitch_mm", "radius_mm", "aperture_mm", "thickness_mm")
        _check(
            "aperture_mm",
            self.aperture_mm,
            self.aperture_mm <= self.pitch_mm,
            f"a lenslet cannot be larger than its cell (≤ pitch_mm = {self.pitch_mm})",
        )
        half_diagonal = self.aperture_mm / math.sqrt(2.0)
        _check(
            "radius_mm",
            self.radius_mm,
            self.radius_mm > half_diagonal,
            f"the sphere must cover the aperture corners (> {half_diagonal:.4f} mm)",
        )
        _check(
            "thickness_mm",
            self.thickness_mm,
            self.thickness_mm > self.corner_sag_mm + 0.2,
            f"must exceed the corner sag {self.corner_sag_mm:.4f} mm by ≥ 0.2 mm of substrate",
        )
        _check("material", self.material, self.material.is_transparent, "a lens must be transparent")
        _check(
            "partial_border_mm",
            self.partial_border_mm,
            0.0 <= self.partial_border_mm < self.pitch_mm,
            f"must lie within 0 ≤ width < pitch_mm = {self.pitch_mm}",
        )

    def sag_mm(self, r_mm: float | Any) -> float | Any:
        """Sag (mm) of a lenslet at radial distance ``r_mm`` (mm) from its vertex."""
        return self.radius_mm - (self.radius_mm**2 - r_mm**2) ** 0.5

    @property
    def corner_sag_mm(self) -> float:
        return float(self.sag_mm(self.aperture_mm / math.sqrt(2.0)))

    @property
    def width_mm(self) -> float:
        """Diced size along x, partial lenslets included, mm."""
        return self.cols * self.pitch_mm + self.partial_border_mm * self._n_partial(Side.PLUS_X, Side.MINUS_X)

    @property
    def length_mm(self) -> float:
        """Diced size along y, partial lenslets included, mm."""
        return self.rows * self.pitch_mm + self.partial_border_mm * self._n_partial(Side.PLUS_Y, Side.MINUS_Y)

    def _n_partial(self, *sides: Side) -> int:
        return sum(side in self.partial_sides for side in sides) if self.partial_border_mm > 0 else 0

    def lenslet_centres_mm(self) -> list[tuple[float, float]]:
        """(x, y) of the full lenslets' vertices in the device frame, mm, row by row."""
        return [
            ((c - (self.cols - 1) / 2) * self.pitch_mm, (r - (self.rows - 1) / 2) * self.pitch_mm)
            for r in range(self.rows)
            for c in range(self.cols)
        ]


@dataclass(frozen=True)
class ApertureMask:
    """Opaque plate over the lenslets that leaves the central array open.

    opening_mm: side of the square opening, mm.
    outer_mm: side of the square plate, mm.
    thickness_mm: plate thickness, mm.
    """

    opening_mm: float
    outer_mm: float
    thickness_mm: float

    def __post_init__(self) -> None:
        _positive(self, "opening_mm", "outer_mm", "thickness_mm")
        _check(
            "outer_mm",
            self.outer_mm,
            self.outer_mm > self.opening_mm + 0.8,
            "must exceed opening_mm by ≥ 0.8 mm (two 0.4-mm rims)",
        )


@dataclass(frozen=True)
class InterferenceFilter:
    """Thin-film band-pass filter on a glass plate.

    width_mm, length_mm, thickness_mm: plate size, mm.
    material: substrate.
    center_nm, bandwidth_nm: nominal passband centre and full width at normal incidence, nm.
    """

    width_mm: float
    length_mm: float
    thickness_mm: float
    material: Material
    center_nm: float
    bandwidth_nm: float

    def __post_init__(self) -> None:
        _positive(self, "width_mm", "length_mm", "thickness_mm")
        _in_range(self, "center_nm", 350.0, 1000.0, " nm")
        _in_range(self, "bandwidth_nm", 1.0, 300.0, " nm")
        _check("material", self.material, self.material.is_transparent, "a filter substrate must be transparent")


@dataclass(frozen=True)
class AbsorptionFilter:
    """Absorbing long-pass film (Wratten gel class).

    width_mm, length_mm, thickness_mm: film size, mm.
    material: film base.
    cut_on_nm: wavelength of 50 % transmission at normal incidence, nm.
    """

    width_mm: float
    length_mm: float
    thickness_mm: float
    material: Material
    cut_on_nm: float

    def __post_init__(self) -> None:
        _positive(self, "width_mm", "length_mm", "thickness_mm")
        _in_range(self, "cut_on_nm", 350.0, 1000.0, " nm")


@dataclass(frozen=True)
class ImagingLayout:
    """Heights of the imaging elements in the device frame.

    film_to_sensor_mm: sensor surface to the absorption film's lower face, mm.
    mla_to_sensor_mm: sensor surface to the MLA's flat face, mm.
    mask_gap_mm: lenslet vertices to the aperture mask's lower face, mm.
    filter_gap_mm: aperture mask's upper face to the emission filter's lower face, mm.
    design_wavelength_nm: wavelength of the paraxial design (focus, magnification), nm.
    """

    film_to_sensor_mm: float
    mla_to_sensor_mm: float
    mask_gap_mm: float
    filter_gap_mm: float
    design_wavelength_nm: float

    def __post_init__(self) -> None:
        _positive(self, "film_to_sensor_mm", "mla_to_sensor_mm")
        _non_negative(self, "mask_gap_mm", "filter_gap_mm")
        _in_range(self, "design_wavelength_nm", 380.0, 1000.0, " nm")


@dataclass(frozen=True)
class ImagedVolume:
    """The object volume the device is designed to image, centred on the nominal focal plane.

    field_mm: lateral field of view (diameter of the illuminated circle), mm.
    depth_mm: axial extent, mm (± depth_mm/2 around the focal plane).
    axial_step_um: axial sampling of reconstructions, µm.
    """

    field_mm: float
    depth_mm: float
    axial_step_um: float

    def __post_init__(self) -> None:
        _positive(self, "field_mm", "depth_mm", "axial_step_um")


# ----------------------------------------------------------------------------- illumination


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
        _positive(self, "emitter_mm", "package_width_mm", "package_length_mm", "package_height_mm", "radiant_flux_mw")
        _in_range(self, "peak_nm", 350.0, 1000.0, " nm")
        _check(
            "emitter_mm",
            self.emitter_mm,
            self.emitter_mm <= min(self.package_width_mm, self.package_length_mm),
            "the emitter must fit on its package",
        )


@dataclass(frozen=True)
class Collimator:
    """Rotationally symmetric freeform TIR collimator in front of each LED, its focus on the
    LED's centre; :mod:`cm2optics.collimator` computes its profile from these numbers.

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
        0 collimates it, more spreads it into a flat-top cone (:mod:`cm2optics.collimator_shaping`).
    tir_spread_deg: output half-angle of the TIR sub-beam's edge ray, degrees (0: collimated).
    tir_crossing: the TIR sub-beam crosses the axis rather than spreading outwards.
    lens_exponent, tir_exponent: exponent γ of each sub-beam's ray mapping tan ψ ∝ F^γ (F the
        sub-beam's flux fraction): 0.5 lights a disc uniformly, smaller pushes power outwards.
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

    @property
    def collimates(self) -> bool:
        """Whether both sub-beams are designed parallel to the axis (no beam shaping)."""
        return self.lens_spread_deg == 0.0 and self.tir_spread_deg == 0.0

    def __post_init__(self) -> None:
        _check("material", self.material, self.material.is_transparent, "a collimator must be transparent")
        _non_negative(self, "led_gap_mm")
        _in_range(self, "lens_half_angle_deg", 5.0, 60.0, "°")
        _positive(self, "cavity_radius_mm", "entry_wall_mm", "footprint_mm", "height_mm", "flange_mm")
        _check("flange_mm", self.flange_mm, self.flange_mm < self.height_mm, f"must be < height_mm = {self.height_mm}")
        _check(
            "entry_wall_mm",
            self.entry_wall_mm,
            self.cavity_radius_mm + self.entry_wall_mm < self.footprint_mm / 2,
            f"the cavity and its wall must fit inside footprint_mm/2 = {self.footprint_mm / 2} "
            f"(cavity_radius_mm + entry_wall_mm = {self.cavity_radius_mm + self.entry_wall_mm})",
        )
        _in_range(self, "lens_spread_deg", 0.0, 40.0, "°")
        _in_range(self, "tir_spread_deg", 0.0, 40.0, "°")
        _in_range(self, "lens_exponent", 0.1, 1.0)
        _in_range(self, "tir_exponent", 0.1, 1.0)


@dataclass(frozen=True)
class LEDArray:
    """Placement of the LED units around the imaging axis.

    count: number of units, evenly spaced in azimuth.
    offset_mm: radial distance from the optical axis of each unit's aperture (the centre of
        the excitation filter's lower face, where light leaves the unit), mm.
    tilt_deg: angle between each unit's axis and the optical axis, degrees; the axis is aimed
        at the centre of the nominal focal plane, which fixes the unit's height.
    azimuth_deg: azimuth of the first unit from +x, degrees.
    excitation_gap_mm: LED emitting surface to the excitation filter's lower face, mm.
    """

    count: int
    offset_mm: float
    tilt_deg: float
    azimuth_deg: float
    excitation_gap_mm: float

    def __post_init__(self) -> None:
        _check("count", self.count, 1 <= self.count <= 12, "must lie within 1–12")
        _positive(self, "offset_mm", "excitation_gap_mm")
        _in_range(self, "tilt_deg", 0.0, 80.0, "°")
        _in_range(self, "azimuth_deg", -360.0, 360.0, "°")


# ----------------------------------------------------------------------------- mechanics


@dataclass(frozen=True)
class Mechanics:
    """Printing and fit rules shared by every printed part.

    clearance_mm: radial gap between a seated part and its seat, mm (0.05–0.2 for a slip fit).
    wall_mm: nominal wall of printed parts, mm.
    min_wall_mm: thinnest wall the printer makes reliably, mm.
    """

    clearance_mm: float
    wall_mm: float
    min_wall_mm: float

    def __post_init__(self) -> None:
        _in_range(self, "clearance_mm", 0.05, 0.2, " mm")
        _in_range(self, "min_wall_mm", 0.2, 2.0, " mm")
        _check("wall_mm", self.wall_mm, self.wall_mm >= self.min_wall_mm, f"must be ≥ min_wall_mm = {self.min_wall_mm}")


@dataclass(frozen=True)
class MLAHousing:
    """Printed housing of the imaging optics, screwed onto the sensor board.

    outer_mm: side of the square tower around the optics, mm.
    flange_mm: thickness of the base flange that carries the screw holes, mm.
    lip_mm: width of the ledges that hold each optic, mm.
    chamfer_mm: 45° chamfer on the tower's top outer edges (room for the tilted LED units), mm.
    """

    outer_mm: float
    flange_mm: float
    lip_mm: float
    chamfer_mm: float

    def __post_init__(self) -> None:
        _positive(self, "outer_mm", "flange_mm", "lip_mm")
        _non_negative(self, "chamfer_mm")


@dataclass(frozen=True)
class LEDHousing:
    """Printed housing of one LED unit: LED seat, collimator seat, excitation filter seat.

    outer_mm: side of the square housing, mm.
    back_mm: thickness of the back wall behind the LED package, mm.
    lip_mm: width of the front lip that retains the excitation filter, mm.
    """

    outer_mm: float
    back_mm: float
    lip_mm: float

    def __post_init__(self) -> None:
        _positive(self, "outer_mm", "back_mm", "lip_mm")


@dataclass(frozen=True)
class BasePlate:
    """Printed dome-shaped plate that holds the LED units around the MLA housing.

    thickness_mm: shell thickness, mm.
    socket_depth_mm: how deep each LED housing sits in its socket, mm.
    """

    thickness_mm: float
    socket_depth_mm: float

    def __post_init__(self) -> None:
        _positive(self, "thickness_mm", "socket_depth_mm")


# ----------------------------------------------------------------------------- the system


@dataclass(frozen=True)
class SystemDesign:
    """One CM² device. ``absorption_filter`` and ``collimator`` may be ``None`` (a V1 device)."""

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

    def __post_init__(self) -> None:
        mla, lay, mech = self.mla, self.imaging, self.mechanics
        if self.absorption_filter is not None:
            film_top = lay.film_to_sensor_mm + self.absorption_filter.thickness_mm
            _check(
                "imaging.film_to_sensor_mm",
                lay.film_to_sensor_mm,
                film_top < lay.mla_to_sensor_mm,
                f"the film (top at {film_top:.3f} mm) must lie below the MLA's flat face at {lay.mla_to_sensor_mm} mm",
            )
        if self.absorption_filter is not None:
            film = self.absorption_filter
            spacer = min(film.width_mm - mla.width_mm, film.length_mm - mla.length_mm) - 2 * self.mla_housing.lip_mm
            _check(
                "absorption_filter.width_mm",
                film.width_mm,
                spacer >= 2 * mech.clearance_mm - 1e-9,
                "the MLA goes into the housing from the sensor side, through the film's ledge: the film must "
                f"exceed the MLA by 2 × (mla_housing.lip_mm + mechanics.clearance_mm) = "
                f"{2 * (self.mla_housing.lip_mm + mech.clearance_mm):.2f} mm along x and y",
            )
        # The corner tabs that hold the MLA from above reach lip_mm over its corners: they span the
        # mask gap plus the depth below the vertices of the lens under the tab's inner edge, at its
        # point nearest a (full) corner lenslet's vertex, or of the land outside the aperture.
        offset = max(mla.pitch_mm / 2 - self.mla_housing.lip_mm / 2, 0.0)
        depth = float(mla.sag_mm(offset * math.sqrt(2.0))) if offset <= mla.aperture_mm / 2 else mla.corner_sag_mm
        tab = lay.mask_gap_mm + depth
        _check(
            "imaging.mask_gap_mm",
            lay.mask_gap_mm,
            tab >= mech.min_wall_mm - 1e-9,
            f"the corner tabs that hold the MLA from above would be {tab:.3f} mm thick "
            f"(< mechanics.min_wall_mm = {mech.min_wall_mm}: not printable); widen the mask gap",
        )
        _check(
            "aperture_mask.opening_mm",
            self.aperture_mask.opening_mm,
            self.aperture_mask.opening_mm <= min(mla.width_mm, mla.length_mm) + 1e-9,
            f"the opening cannot exceed the MLA ({mla.width_mm:.3f} × {mla.length_mm:.3f} mm)",
        )
        seat = max(self.emission_filter.width_mm, self.emission_filter.length_mm, self.aperture_mask.outer_mm)
        _check(
            "mla_housing.outer_mm",
            self.mla_housing.outer_mm,
            self.mla_housing.outer_mm >= seat + 2 * (mech.clearance_mm + mech.wall_mm),
            f"the tower must hold a {seat} mm seat with walls: ≥ {seat + 2 * (mech.clearance_mm + mech.wall_mm):.2f} mm",
        )
        top_wall = (self.mla_housing.outer_mm - seat) / 2 - mech.clearance_mm - self.mla_housing.chamfer_mm
        _check(
            "mla_housing.chamfer_mm",
            self.mla_housing.chamfer_mm,
            top_wall >= mech.min_wall_mm - 1e-9,
            f"the chamfer leaves a {top_wall:.3f}-mm wall at the tower top (< min_wall_mm = {mech.min_wall_mm})",
        )
        _check(
            "mla_housing.outer_mm",
            self.mla_housing.outer_mm,
            self.mla_housing.outer_mm
            < self.sensor_board.hole_spacing_mm - self.sensor_board.hole_diameter_mm - 2 * mech.wall_mm,
            "the tower must leave room for the board's screw holes",
        )
        if self.collimator is not None:
            pocket = self.collimator.footprint_mm + 2 * (mech.clearance_mm + mech.min_wall_mm)
            _check(
                "collimator.footprint_mm",
                self.collimator.footprint_mm,
                pocket <= self.led_housing.outer_mm,
                f"a collimator wider than its housing: footprint + clearance + walls = {pocket:.2f} mm "
                f"> led_housing.outer_mm = {self.led_housing.outer_mm}",
            )
            exit_z = self.collimator.led_gap_mm + self.collimator.height_mm
            _check(
                "led_array.excitation_gap_mm",
                self.led_array.excitation_gap_mm,
                abs(self.led_array.excitation_gap_mm - exit_z) <= 1e-6,
                f"must equal collimator.led_gap_mm + height_mm = {exit_z:g}: the excitation filter rests on the "
                "collimator's exit face (a printed spacer in a smaller gap would be thinner than a printable wall)",
            )
        filt = max(self.excitation_filter.width_mm, self.excitation_filter.length_mm)
        _check(
            "excitation_filter.width_mm",
            filt,
            filt + 2 * (mech.clearance_mm + mech.min_wall_mm) <= self.led_housing.outer_mm,
            f"the excitation filter must fit its housing (led_housing.outer_mm = {self.led_housing.outer_mm})",
        )
        package = max(self.led.package_width_mm, self.led.package_length_mm)
        _check(
            "led.package_width_mm",
            package,
            package + 2 * (mech.clearance_mm + mech.min_wall_mm) <= self.led_housing.outer_mm,
            f"the LED package must fit its housing (led_housing.outer_mm = {self.led_housing.outer_mm})",
        )
        _check(
            "imaging.mla_to_sensor_mm",
            lay.mla_to_sensor_mm,
            self.paraxial_magnification > 0.05,
            "the sensor must lie beyond the lenslets' back focus (no real image of the sample otherwise)",
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

    @cached_property
    def object_plane_z_mm(self) -> float:
        """Height of the nominal focal plane, mm: the plane of best focus.

        The height of an on-axis point source whose image through a lenslet has the least RMS
        wavefront error on the sensor (over the lenslet's square aperture, at the design
        wavelength; exact ray trace, :func:`cm2optics.focus.best_focus_height_mm`). The lenslets' spherical
        aberration puts it :attr:`focus_shift_mm` nearer the device than the paraxial conjugate
        of the sensor (:attr:`paraxial_object_plane_z_mm`). It is where the PSFs are sharpest,
        where a lab centres its calibration scan and puts its sample: object-space ``z`` of scans
        and volumes (DESIGN.md) is measured from this plane.
        """
        from cm2optics.focus import best_focus_height_mm

        return best_focus_height_mm(self)

    @property
    def paraxial_object_plane_z_mm(self) -> float:
        """Height of the paraxial conjugate of the sensor (first-order optics), mm."""
        return float(self.emission_filter_z_mm + self.emission_filter.thickness_mm + self._object_distance_mm)

    @property
    def focus_shift_mm(self) -> float:
        """Paraxial conjugate minus the plane of best focus, mm (> 0: best focus nearer the device,
        as for under-corrected spherical aberration)."""
        return self.paraxial_object_plane_z_mm - self.object_plane_z_mm

    @property
    def working_distance_mm(self) -> float:
        """Nominal focal plane to the lenslet vertices, mm."""
        return self.object_plane_z_mm - self.mla_vertex_z_mm

    def object_z_to_height_mm(self, z_mm: float) -> float:
        """Object-space z (mm from the focal plane, +z towards the device) → device-frame height."""
        return self.object_plane_z_mm - z_mm

    # -- paraxial imaging through one lenslet ---------------------------------------------
    @cached_property
    def _lenslet_system(self) -> Any:
        """ABCD matrix from the emission filter's front face to the sensor surface."""
        lam = self.imaging.design_wavelength_nm
        n_filter = refractive_index(self.emission_filter.material, lam)
        n_lens = refractive_index(self.mla.material, lam)
        air = 1.0
        elements = [
            paraxial.propagate(self.emission_filter.thickness_mm, n_filter),
            paraxial.propagate(self.emission_filter_z_mm - self.mla_vertex_z_mm, air),
            paraxial.refract(self.mla.radius_mm, air, n_lens),
            paraxial.propagate(self.mla.thickness_mm, n_lens),
            paraxial.refract(math.inf, n_lens, air),
        ]
        gap_below = self.imaging.mla_to_sensor_mm
        if self.absorption_filter is not None:
            n_film = refractive_index(self.absorption_filter.material, lam)
            film_top = self.imaging.film_to_sensor_mm + self.absorption_filter.thickness_mm
            elements += [
                paraxial.propagate(gap_below - film_top, air),
                paraxial.propagate(self.absorption_filter.thickness_mm, n_film),
            ]
            gap_below = self.imaging.film_to_sensor_mm
        elements.append(paraxial.propagate(gap_below, air))
        return paraxial.chain(*elements)

    @property
    def lenslet_focal_length_mm(self) -> float:
        """Effective focal length of one lenslet at the design wavelength, mm."""
        n_lens = refractive_index(self.mla.material, self.imaging.design_wavelength_nm)
        return self.mla.radius_mm / (n_lens - 1.0)

    @property
    def _object_distance_mm(self) -> float:
        return paraxial.conjugate_object_distance_mm(self._lenslet_system)

    @property
    def paraxial_magnification(self) -> float:
        """Lateral magnification |m| of each lenslet between the sensor and its paraxial conjugate."""
        return float(abs(paraxial.lateral_magnification(self._lenslet_system, self._object_distance_mm)))

    @property
    def magnification(self) -> float:
        """Lateral magnification |m| of each lenslet at the nominal focal plane (best focus): where
        the chief ray (through the lenslet's vertex, its stop) from a source in that plane lands
        on the sensor, per mm of source height. What a calibration scan measures there."""
        from cm2optics.focus import chief_ray_magnification

        return chief_ray_magnification(self, self.object_plane_z_mm)

    @property
    def object_pixel_um(self) -> float:
        """Sensor pixel projected into object space, µm."""
        return self.sensor.pixel_um / self.magnification

    @property
    def object_na(self) -> float:
        """Object-side numerical aperture of one lenslet (square aperture, inscribed circle)."""
        return math.sin(math.atan(self.mla.aperture_mm / 2 / self.working_distance_mm))

    # -- files ------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return _to_plain(self)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False, allow_unicode=True)

    def save(self, path: str | Path) -> None:
        """Write the design as YAML (atomically)."""
        from cm2optics.io import write_text_atomic

        write_text_atomic(Path(path), self.to_yaml())

    def parameter_hash(self) -> str:
        """Short SHA-256 of the canonical design, for manifests and caches."""
        text = json.dumps(self.to_dict(), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def with_changes(self, changes: dict[str, Any]) -> SystemDesign:
        """A copy with dotted-path fields replaced (``{"mla.radius_mm": 1.7}``), validated anew."""
        data = self.to_dict()
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
        return design_from_dict(data)


# ----------------------------------------------------------------------------- YAML edge


def _to_plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return {f.name: _to_plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, tuple):
        return [_to_plain(v) for v in value]
    return value


def _type_name(tp: Any) -> str:
    if isinstance(tp, type):
        if issubclass(tp, Enum):
            return "one of " + ", ".join(repr(m.value) for m in tp)
        if dataclasses.is_dataclass(tp):
            return "a mapping of fields"
        return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}.get(tp, tp.__name__)
    return str(tp)


def _coerce(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, path)
    if origin is tuple:
        item_type = typing.get_args(tp)[0]
        if not isinstance(value, (list, tuple)):
            raise DesignError(path, value, f"must be a list of {_type_name(item_type)}")
        return tuple(_coerce(item_type, v, f"{path}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        return _dataclass_from_dict(tp, value, path)
    if isinstance(tp, type) and issubclass(tp, Enum):
        try:
            return tp(value)
        except ValueError:
            raise DesignError(path, value, f"must be {_type_name(tp)}") from None
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise DesignError(path, value, "must be a number")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise DesignError(path, value, "must be an integer")
        return value
    if tp is bool and not isinstance(value, bool):
        raise DesignError(path, value, "must be true or false")
    if tp is str and not isinstance(value, str):
        raise DesignError(path, value, "must be a string")
    return value


def _dataclass_from_dict(cls: type, data: Any, path: str) -> Any:
    prefix = f"{path}." if path else ""
    if not isinstance(data, dict):
        raise DesignError(path or "<design>", data, "must be a mapping of fields")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in fields(cls)]
    for key in data:
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise DesignError(
                f"{prefix}{key}", data[key], f"unknown field{hint}; {cls.__name__} has: {', '.join(names)}"
            )
    for name in names:
        if name not in data:
            raise DesignError(f"{prefix}{name}", None, f"missing; expected {_type_name(hints[name])}")
    kwargs = {name: _coerce(hints[name], data[name], f"{prefix}{name}") for name in names}
    try:
        return cls(**kwargs)
    except DesignError as error:
        if error.field.startswith(prefix) and prefix:
            raise
        raise DesignError(f"{prefix}{error.field}", error.value, error.allowed) from None


def design_from_dict(data: dict[str, Any]) -> SystemDesign:
    """Build and validate a :class:`SystemDesign` from plain data (as parsed from YAML)."""
    return _dataclass_from_dict(SystemDesign, data, "")


def load_design(path: str | Path) -> SystemDesign:
    """Load and validate a design YAML file."""
    path = Path(path)
    if not path.is_file():
        raise DesignError("design", str(path), "no such file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise DesignError("design", str(path), f"is not valid YAML ({error})") from None
    return design_from_dict(data)


def available_presets() -> list[str]:
    """Names of the presets shipped with the package."""
    folder = resources.files("cm2optics") / "presets"
    return sorted(p.name.removesuffix(".yaml") for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_preset(name: str) -> SystemDesign:
    """Load a shipped preset by name (``cm2-v2``, ``cm2-v1``) or a YAML path."""
    if name.endswith((".yaml", ".yml")):
        return load_design(name)
    presets = available_presets()
    if name not in presets:
        raise DesignError("preset", name, f"unknown preset; available: {', '.join(presets)} (or a path to a .yaml)")
    text = (resources.files("cm2optics") / "presets" / f"{name}.yaml").read_text()
    return design_from_dict(yaml.safe_load(text))
