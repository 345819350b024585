"""Simulators the calibration loop can drive: a model of the device's images whose parameters
include the effects of :mod:`.effects`.

A simulator returns, for source positions (N, 3) mm and effect values (effect key → parameters),
the images (N, y, x) in counts per ms of a unit source, with the optical effects included and the
sensor displaced by a frame offset (rendered in place: a resampled image of ≈ 1-px foci would be
wrong); the
sensor-side effects (stray light, crosstalk, leakage) are added by :mod:`.effects` on top of any
simulator. :class:`AnalyticSimulator` is the fast closed-form CM²-like model
(:mod:`cm2optics.lsv.toy`), used by the tests and as the quick first pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from cm2optics.calibrate.effects import Effect, split_key
from cm2optics.lsv.toy import AnalyticCM2
from cm2optics.optics.tilt import tilt_matrix

Values = dict[str, dict[str, float]]


class Simulator(Protocol):
    """What the attribution needs of a model of the device."""

    lenslets: int
    pixel_um: float
    shape: tuple[int, int]

    def supports(self, effect: Effect) -> bool: ...

    def rates(
        self, positions_mm: np.ndarray, values: Values, offset_px: tuple[float, float] = (0.0, 0.0)
    ) -> np.ndarray: ...

    def focus_centres_px(self, positions_mm: np.ndarray) -> np.ndarray: ...

    def pitch_px(self) -> float: ...


OPTICAL = {
    "mla_decenter",
    "mla_rotation",
    "lenslet_pitch",
    "lenslet_decenter",
    "lenslet_transmission",
    "source_profile",
    "vignetting",
    "mla_spacing",
    "mla_tilt",
    "sensor_tilt",
    "partial_lenslets",
    "source_size",
}


@dataclass(frozen=True)
class AnalyticSimulator:
    """The analytic CM²-like model with the library's optical effects.

    model: the nominal analytic model (its lenslet centres are the design's).
    spacing_magnification_per_mm: d(ln m)/d(MLA–sensor spacing), 1/mm, from the design's
        first-order optics (a larger spacing images a nearer plane, larger).

    A tilted array (``mla_tilt``) raises lenslet j by δ_j = y_j·sin θx − x_j·sin θy (the
    convention of :mod:`cm2optics.optics.tilt`): its magnification × exp(k·δ_j) as for a spacing
    change, its best focus moved by −δ_j·(1 + 1/m₀²) in object space (the lens nearer the
    object by δ_j, its image distance longer by δ_j). Partial lenslets on a side
    (``partial_lenslets[side]``, ``border_mm`` wide) are the cells one pitch beyond the array's
    edge, their foci carrying border/pitch of a full lenslet's light. A source larger than a point
    (``source_size``, ``diameter_um``) widens every focus by its disc image's second moment
    (:class:`~cm2optics.lsv.toy.AnalyticCM2`'s ``source_diameter_um``).
    """

    model: AnalyticCM2
    spacing_magnification_per_mm: float

    @property
    def lenslets(self) -> int:
        return self.model.rows * self.model.cols

    @property
    def pixel_um(self) -> float:
        return self.model.pixel_um

    @property
    def shape(self) -> tuple[int, int]:
        return self.model.shape

    def supports(self, effect: Effect) -> bool:
        return effect.name in OPTICAL or effect.name in {"stray_light", "pixel_crosstalk", "leakage_background"}

    def pitch_px(self) -> float:
        c = np.asarray(self.model.lenslet_centres_mm, float)
        distances = np.hypot(*(c[:, None, :] - c[None, :, :]).transpose(2, 0, 1))
        return float(np.min(distances[distances > 0])) * 1000.0 / self.model.pixel_um

    def _model_with(self, values: Values) -> tuple[AnalyticCM2, np.ndarray, float]:
        """The analytic model with the optical effects, per-lenslet flux weights, the source's falloff."""
        centres = np.asarray(self.model.lenslet_centres_mm, float).copy()
        weights = np.ones(len(centres))
        changes: dict[str, object] = {}
        falloff = 0.0
        pitch = self.pitch_px() * self.model.pixel_um / 1000.0
        for key, p in values.items():
            name, index = split_key(key)
            if name == "partial_lenslets" and p["border_mm"] > 0:
                extra = _partial_centres(centres[: self.lenslets], index, pitch)
                centres = np.vstack([centres, extra])
                weights = np.concatenate([weights, np.full(len(extra), p["border_mm"] / pitch)])
        for key, p in values.items():
            name, j = split_key(key)
            if name == "lenslet_pitch":
                centres = centres * (pitch + p["delta_mm"]) / pitch
            elif name == "lenslet_decenter":
                centres[j] += (p["dx_mm"], p["dy_mm"])
            elif name == "lenslet_transmission":
                weights[j] *= p["transmission"]
            elif name == "source_profile":
                falloff = p["falloff_per_rad2"]
            elif name == "vignetting":
                changes["vignetting_mm"] = self.model.vignetting_mm + p["radius_delta_mm"]
            elif name == "mla_spacing":
                changes["magnification"] = self.model.magnification * math.exp(
                    self.spacing_magnification_per_mm * p["delta_mm"]
                )
            elif name == "source_size":
                changes["source_diameter_um"] = p["diameter_um"]
            elif name == "sensor_tilt":
                changes["sensor_tilt_deg"] = (p["tilt_x_deg"], p["tilt_y_deg"])
            elif name == "mla_tilt":
                normal = tilt_matrix(p["tilt_x_deg"], p["tilt_y_deg"])[:, 2]
                raised = -(centres @ normal[:2]) / normal[2]  # δ_j: each vertex's height change, mm
                m0 = self.model.magnification
                changes["lenslet_magnification"] = tuple(np.exp(self.spacing_magnification_per_mm * raised))
                changes["lenslet_focus_mm"] = tuple(-raised * (1.0 + 1.0 / m0**2))
        for key, p in values.items():  # whole-array motions act on the (possibly perturbed) lattice
            if key == "mla_rotation":
                a = math.radians(p["angle_deg"])
                rotation = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
                centres = centres @ rotation.T
            elif key == "mla_decenter":
                centres = centres + (p["dx_mm"], p["dy_mm"])
        changes["lenslet_centres_mm"] = tuple(map(tuple, centres))
        return replace(self.model, **changes), weights, falloff

    def rates(
        self, positions_mm: np.ndarray, values: Values, offset_px: tuple[float, float] = (0.0, 0.0)
    ) -> np.ndarray:
        """Images (N, y, x) in counts per ms of a unit source, the sensor displaced by ``offset_px``
        (row, col) px: rendered there, not resampled, so undersampled foci stay exact."""
        model, weights, falloff = self._model_with(values)
        model = replace(model, offset_px=(float(offset_px[0]), float(offset_px[1])))
        centres = np.asarray(model.lenslet_centres_mm, float)
        out = np.empty((len(positions_mm),) + model.shape, np.float32)
        for i, (x, y, z) in enumerate(np.asarray(positions_mm, float)):
            rho = np.hypot(centres[:, 0] - x, centres[:, 1] - y)
            theta = np.arctan2(rho, model.reduced_distance_mm - z)  # from the source to each lenslet, rad
            w = weights * np.exp(-2.0 * falloff * theta**2)
            out[i] = model.image(x, y, z, weights=w) * 1000.0  # the analytic source delivers 1000 units/ms
        return out

    def focus_centres_px(self, positions_mm: np.ndarray) -> np.ndarray:
        return np.stack([self.model.foci(*p)[0] for p in np.asarray(positions_mm, float)])


def _partial_centres(centres: np.ndarray, side: str, pitch_mm: float) -> np.ndarray:
    """Vertices (k, 2) mm of the partial cells one pitch beyond the array's ``side`` edge."""
    axis = 0 if side[1] == "x" else 1
    sign = 1.0 if side[0] == "+" else -1.0
    edge = centres[:, axis].max() if sign > 0 else centres[:, axis].min()
    row = centres[np.isclose(centres[:, axis], edge)].copy()
    row[:, axis] += sign * pitch_mm
    return row
