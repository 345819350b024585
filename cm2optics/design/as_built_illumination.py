"""The illumination as built: how the assembled LED units depart from their design (YAML
section ``illumination_as_built:``).

Every field defaults to the nominal value, so a design without the section, or with every field
at its default, illuminates as designed: its YAML and its
:meth:`~cm2optics.design.SystemDesign.parameter_hash` are unchanged. The fields are the
parameters of the illumination effects of the calibration (:mod:`cm2optics.calibrate.illumination`),
in the same units and ranges, and ``cm2 illum run`` honours them
(:func:`cm2optics.illumination.as_built.as_built_scene`):

- ``led_flux``: each LED's radiant flux relative to the design's ``led.radiant_flux_mw``
  (binning, ageing, a weaker drive current): the unit emits that many more or fewer rays of
  the same power;
- ``led_tilt_deg``: each whole unit (LED, collimator, filter, housing) turned about its LED's
  centre, about the unit's own x and then y axis, degrees;
- ``collimator_decenter_mm``: each unit's collimator (with its filter and housing) displaced
  in the LED's plane relative to its LED, mm; traced as the LED moved the other way (the
  same relative decentre; the beam's origin differs by the decentre itself, ≤ 0.3 mm).

Units are numbered as :func:`cm2optics.optics.layout.led_poses` places them (the first at
``led_array.azimuth_deg``, counter-clockwise); every per-unit list has one entry per unit
(``led_array.count``) or none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from cm2optics.design.validation import DesignError

__all__ = ["COLLIMATOR_DECENTER_MM", "LED_FLUX", "LED_TILT_DEG", "IlluminationAsBuilt"]

LED_FLUX = (0.0, 2.0)  # relative flux range
LED_TILT_DEG = 5.0  # |tilt| about each axis ≤ this, degrees
COLLIMATOR_DECENTER_MM = 0.3  # |dx|, |dy| ≤ this, mm


def _check_pairs(name: str, pairs: tuple[tuple[float, ...], ...], limit: float, unit: str) -> None:
    for j, pair in enumerate(pairs):
        if len(pair) != 2 or not all(math.isfinite(v) and abs(v) <= limit for v in pair):
            raise DesignError(f"{name}[{j}]", list(pair), f"must be a pair of numbers within ±{limit}{unit}")


@dataclass(frozen=True)
class IlluminationAsBuilt:
    """Departures of the built LED units from their design; every default is the nominal value.

    led_flux: per unit its radiant flux relative to the design's, 0–2; empty: all 1.
    led_tilt_deg: per unit [about x, about y] of the unit's tilt, degrees, each within ±5; empty: none.
    collimator_decenter_mm: per unit [dx, dy] of its collimator relative to its LED (LED
        frame), mm, each within ±0.3; empty: none.
    """

    led_flux: tuple[float, ...] = ()
    led_tilt_deg: tuple[tuple[float, ...], ...] = ()
    collimator_decenter_mm: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        low, high = LED_FLUX
        for j, value in enumerate(self.led_flux):
            if not (math.isfinite(value) and low <= value <= high):
                raise DesignError(f"led_flux[{j}]", value, f"must lie within {low}–{high}")
        _check_pairs("led_tilt_deg", self.led_tilt_deg, LED_TILT_DEG, "°")
        _check_pairs("collimator_decenter_mm", self.collimator_decenter_mm, COLLIMATOR_DECENTER_MM, " mm")

    def changed(self) -> dict[str, Any]:
        """The fields that differ from their defaults (plain data, as written to YAML)."""
        out: dict[str, Any] = {}
        if any(v != 1 for v in self.led_flux):
            out["led_flux"] = list(self.led_flux)
        for name in ("led_tilt_deg", "collimator_decenter_mm"):
            pairs = getattr(self, name)
            if any(v != 0 for pair in pairs for v in pair):
                out[name] = [list(pair) for pair in pairs]
        return out

    @property
    def is_nominal(self) -> bool:
        return not self.changed()

    def flux(self, unit: int) -> float:
        """Relative flux of ``unit`` (1 where the list is empty)."""
        return float(self.led_flux[unit]) if unit < len(self.led_flux) else 1.0

    def tilt_deg(self, unit: int) -> tuple[float, float]:
        """Tilt of ``unit`` about its x and y axes, degrees."""
        return _pair(self.led_tilt_deg, unit)

    def decenter_mm(self, unit: int) -> tuple[float, float]:
        """Decentre (dx, dy) of ``unit``'s collimator relative to its LED, mm."""
        return _pair(self.collimator_decenter_mm, unit)


def _pair(pairs: tuple[tuple[float, ...], ...], unit: int) -> tuple[float, float]:
    if unit < len(pairs):
        a, b = pairs[unit]
        return float(a), float(b)
    return 0.0, 0.0
