"""The device as built: how an assembled CM² departs from its design (YAML section ``as_built:``).

Every field defaults to the nominal value (the effect is absent), so a design without the
section, or with every field at its default, is the design as drawn: its YAML and its
:meth:`~cm2optics.design.SystemDesign.parameter_hash` are unchanged (``to_dict`` writes only the
fields that differ from their defaults). The fields are the physical parameters of the
calibration's effect library (:mod:`cm2optics.calibrate.effects`), with the same units and
ranges, so that a fitted effect is a design value that every stage honours:

- the array's geometry (decentre, rotation, pitch, single lenslets displaced) shapes the cells
  of :func:`cm2optics.optics.lenslets.lens_cells`, which the emission tracer consumes (the MLA–
  sensor spacing is the design's own ``imaging.mla_to_sensor_mm``);
- a lenslet's transmission scales its focus, the sensor offset shifts the pixel grid
  (:mod:`cm2optics.emission.psf`), the vignetting delta widens or narrows the mask's opening as
  the tracer sees it (:mod:`cm2optics.emission.optics`);
- stray light, leakage and pixel crosstalk act on the images
  (:func:`cm2optics.calibrate.effects.apply_image_effects`, applied by ``cm2 psf simulate``);
- the tilts of the array (about the centre of its vertex plane) and of the sensor (about its
  centre) are traced exactly: the emission tracer follows the rays into the tilted array's frame
  and lands them on the tilted sensor plane (:mod:`cm2optics.emission.trace`; the convention of
  :mod:`cm2optics.optics.tilt`).

The sensor offset moves the pixel grid only: the active area's edges, where the tracer drops
rays, stay centred on the axis (for offsets ≪ the sensor's half-width this matters only to
foci at its very edge). The illumination path (``cm2 illum run``) reads its own section,
``illumination_as_built`` (:mod:`cm2optics.design.as_built_illumination`).

Lenslets are numbered row by row over the full cells (``j = row · cols + col``), as in
:meth:`cm2optics.design.MicrolensArray.lenslet_centres_mm`; partial cells left by dicing move
with the array but take no per-lenslet values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from cm2optics.design.validation import DesignError, in_range

__all__ = ["AsBuilt"]


#: field → (low, high, unit) of the scalar fields.
RANGES: dict[str, tuple[float, float, str]] = {
    "mla_decenter_x_mm": (-0.2, 0.2, " mm"),
    "mla_decenter_y_mm": (-0.2, 0.2, " mm"),
    "mla_rotation_deg": (-3.0, 3.0, "°"),
    "mla_tilt_x_deg": (-5.0, 5.0, "°"),
    "mla_tilt_y_deg": (-5.0, 5.0, "°"),
    "lenslet_pitch_delta_mm": (-0.05, 0.05, " mm"),
    "sensor_offset_x_um": (-1000.0, 1000.0, " µm"),
    "sensor_offset_y_um": (-1000.0, 1000.0, " µm"),
    "sensor_tilt_x_deg": (-5.0, 5.0, "°"),
    "sensor_tilt_y_deg": (-5.0, 5.0, "°"),
    "stray_light_fraction": (0.0, 0.5, ""),
    "stray_light_width_um": (20.0, 2000.0, " µm"),
    "leakage_counts_per_ms": (0.0, 1e4, " counts/ms"),
    "pixel_crosstalk_fraction": (0.0, 0.5, ""),
    "vignetting_radius_delta_mm": (-1.0, 1.0, " mm"),
}
LENSLET_DECENTER_MM = 0.1  # |dx|, |dy| ≤ this, mm
LENSLET_TRANSMISSION = (0.0, 1.5)


@dataclass(frozen=True)
class AsBuilt:
    """Departures of the built device from its design; every default is the nominal value.

    mla_decenter_x_mm, mla_decenter_y_mm: the whole array displaced across the sensor (x along
        rows, y along columns), mm, ±0.2.
    mla_rotation_deg: the array rotated about the optical axis (counter-clockwise from +x to +y,
        about the central lenslet's nominal axis), degrees, ±3.
    mla_tilt_x_deg, mla_tilt_y_deg: the array tilted right-handedly about x, then y, about the
        centre of its vertex plane, degrees, ±5.
    lenslet_pitch_delta_mm: lenslet pitch minus the design's ``mla.pitch_mm``, mm, ±0.05 (the
        lattice scales about the central lenslet).
    lenslet_decenter_mm: per full lenslet (row by row) its [dx, dy] within the array, mm, each
        within ±0.1; empty: none displaced.
    lenslet_transmission: per full lenslet (row by row) the fraction of its nominal light it
        passes (dust, a defect), 0–1.5; empty: all 1.
    sensor_offset_x_um, sensor_offset_y_um: the sensor displaced along +x, +y relative to the
        optics, µm, ±1000 (the image moves the other way on the pixel grid).
    sensor_tilt_x_deg, sensor_tilt_y_deg: the sensor tilted right-handedly about x, then y, about
        its centre, degrees, ±5: at (x, y) it sits ≈ y·sin θx − x·sin θy above z = 0.
    stray_light_fraction: fraction of each focus's light spread into a wide Gaussian halo
        (scatter in the housing and filters), 0–0.5.
    stray_light_width_um: σ of that halo on the sensor, µm, 20–2000 (default 200).
    leakage_counts_per_ms: uniform light reaching every pixel (excitation leaking through the
        filters), counts per ms of exposure, 0–1e4.
    pixel_crosstalk_fraction: fraction of each pixel's signal shared with its four neighbours, 0–0.5.
    vignetting_radius_delta_mm: the clear aperture that cuts off the foci of sources far off a
        lenslet's axis (the mask's opening, half-width) minus the design's, mm, ±1.
    """

    mla_decenter_x_mm: float = 0.0
    mla_decenter_y_mm: float = 0.0
    mla_rotation_deg: float = 0.0
    mla_tilt_x_deg: float = 0.0
    mla_tilt_y_deg: float = 0.0
    lenslet_pitch_delta_mm: float = 0.0
    lenslet_decenter_mm: tuple[tuple[float, ...], ...] = ()
    lenslet_transmission: tuple[float, ...] = ()
    sensor_offset_x_um: float = 0.0
    sensor_offset_y_um: float = 0.0
    sensor_tilt_x_deg: float = 0.0
    sensor_tilt_y_deg: float = 0.0
    stray_light_fraction: float = 0.0
    stray_light_width_um: float = 200.0
    leakage_counts_per_ms: float = 0.0
    pixel_crosstalk_fraction: float = 0.0
    vignetting_radius_delta_mm: float = 0.0

    def __post_init__(self) -> None:
        for name, (low, high, unit) in RANGES.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise DesignError(name, value, "must be a number")
            in_range(self, name, low, high, unit)
        for j, pair in enumerate(self.lenslet_decenter_mm):
            name = f"lenslet_decenter_mm[{j}]"
            if len(pair) != 2:
                raise DesignError(name, list(pair), "must be a pair [dx, dy] in mm")
            if not all(math.isfinite(v) and abs(v) <= LENSLET_DECENTER_MM for v in pair):
                raise DesignError(name, list(pair), f"dx and dy must lie within ±{LENSLET_DECENTER_MM} mm")
        low, high = LENSLET_TRANSMISSION
        for j, value in enumerate(self.lenslet_transmission):
            if not (math.isfinite(value) and low <= value <= high):
                raise DesignError(f"lenslet_transmission[{j}]", value, f"must lie within {low}–{high}")

    # -- what differs from the design -------------------------------------------------------
    def changed(self) -> dict[str, Any]:
        """The fields that differ from their defaults (plain data, as written to YAML)."""
        default = AsBuilt()
        out: dict[str, Any] = {}
        for f in fields(self):
            value, nominal = getattr(self, f.name), getattr(default, f.name)
            if f.name == "lenslet_decenter_mm":
                if any(v != 0 for pair in value for v in pair):
                    out[f.name] = [list(pair) for pair in value]
            elif f.name == "lenslet_transmission":
                if any(v != 1 for v in value):
                    out[f.name] = list(value)
            elif value != nominal:
                out[f.name] = value
        return out

    @property
    def is_nominal(self) -> bool:
        return not self.changed()

    def lenslet_offset_mm(self, j: int) -> tuple[float, float]:
        """(dx, dy) of full lenslet ``j`` within the array, mm."""
        if j < len(self.lenslet_decenter_mm):
            dx, dy = self.lenslet_decenter_mm[j]
            return float(dx), float(dy)
        return 0.0, 0.0

    def transmission(self, j: int) -> float:
        """Transmission of full lenslet ``j`` (1 where the list is empty)."""
        return float(self.lenslet_transmission[j]) if j < len(self.lenslet_transmission) else 1.0

    def image_effects(self) -> dict[str, dict[str, float]]:
        """The sensor-side effects in the vocabulary of :func:`cm2optics.calibrate.effects.apply_image_effects`
        (only those present)."""
        out: dict[str, dict[str, float]] = {}
        if self.stray_light_fraction > 0:
            out["stray_light"] = {"fraction": self.stray_light_fraction, "width_um": self.stray_light_width_um}
        if self.pixel_crosstalk_fraction > 0:
            out["pixel_crosstalk"] = {"fraction": self.pixel_crosstalk_fraction}
        if self.leakage_counts_per_ms > 0:
            out["leakage_background"] = {"counts_per_ms": self.leakage_counts_per_ms}
        return out
