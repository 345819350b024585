"""Calibrate the illumination against a measured map: residual before, effects found, residual after.

:func:`calibrate_illumination` is what ``cm2 calibrate illumination`` runs. The measured map is
an image of a uniform fluorescent slide on the sample plane: its rows run along +y and its
columns along +x of the device frame (as ``cm2 illum run``'s maps), its centre on the optical
axis, ``pixel_um`` its pixel on the sample. Map and model are compared at the centres of a
square grid of pitch ``bin_mm`` over the field's circle, each value the average under the same
tent (bilinear, cloud-in-cell) kernel, one pitch wide on each side: the image's pixels are
weighted by it, and every ray of the model's irradiance map — traced by the same tracer as
``cm2 illum run``, with the design's ``illumination_as_built`` — shares its power among the four
nearest centres by it. A ray's share then changes smoothly as the ray moves, so a tilt or a
decentre, which moves a unit's rays together (a collimator decentre moves them ≈ 12× as far on
the sample), changes the model smoothly; with box bins every ray crossing a bin's edge was a
jump, and the χ² along a decentre, traced with common random numbers, was as rough as the
decentre's own signal (BENCHMARKS.md).

Registration (nuisance, always free): one global scale (the exposure, the dye's brightness and
the camera's gain are unknown) and one lateral offset (x, y, mm; the camera's centre on the
axis). Noise: shot noise of the camera, ``counts_per_electron × model`` per pixel (averaged
over the kernel's effective number of pixels, (Σw)²/Σw²), plus the model's own Monte Carlo
variance (every ray's power times its weight, squared, per centre). Neighbouring centres share
pixels and rays, so their noise is correlated — by ¼ one pitch apart along an axis, 1/16
diagonally (:data:`TENT_NEIGHBOUR_CORRELATION`) — and χ² is the generalised one, the residual over
σ decorrelated by that correlation's Cholesky factor: a matching model's χ² is then χ² of n − k
degrees of freedom, and the BIC, the uncertainties and the "unexplained" floor hold. (Weighted by
σ alone, a smooth residual's χ² reads up to (1 + 2·¼)² = 2.25× too large: a smooth pattern's
noise averaged over many centres is that of box bins, while each centre's σ is 1/1.5 of a box
bin's; measured on noise-only maps, the test.)

Effects (:func:`illumination_effects`, the fields of
:class:`~cm2optics.design.as_built_illumination.IlluminationAsBuilt`): ``led_flux`` (a unit's
relative radiant flux; linear — each unit's map is traced once and weighted), ``led_tilt``
(the unit turned about its LED, degrees) and ``collimator_decenter`` (mm), both by finite
differences on re-traces with the same rays (common random numbers). Relative fluxes are
relative to the units left at nominal (the global scale absorbs the rest: a map cannot tell one
LED at 70 % from three at 143 %).

Attribution as for scans (:mod:`.attribute`): every candidate is fitted, linearised, beside the
nuisance and the effects already kept; the ``REFITTED_CANDIDATES`` that lower the BIC (χ² + k ln n)
most are refitted by Gauss–Newton with the tracer in the loop, and the best of them is kept if it
lowers the BIC by more than ``BIC_THRESHOLD`` — a traced one also, on average, on
``HELD_OUT_TRACES`` models traced with independent rays (seeds seed + 1 …), by more than
``HELD_OUT_Z`` standard deviations of that mean under no improvement (:func:`_held_out_threshold`):
a tilt or decentre fitted to the model's own Monte Carlo noise does not lower it there. A geometry
that moves a unit's beam by more than a bin (a 0.15-mm decentre: ≈ 1.9 mm) shares almost no rays
with the nominal trace, so on one held-out trace the two χ² are independent draws and their
difference varies by ≈ ± 29; one such trace passed a false decentre on 3 of 10 clean maps
(BENCHMARKS.md, session 13). With a realistic map, whose camera noise is far below the model's,
that noise limits detection; the search stops when no candidate is significant (the BIC alone: a
map has few bins, so χ²_red may sit a little above ``CHI2_FLOOR`` with a significant effect left;
above it after the effects, the residual is described as unexplained).
When a tilt or decentre is kept, every kept value is refitted last (Gauss–Newton, central
differences) on the model traced with ``POLISH_RAYS_FACTOR`` × the rays (common random numbers
between its nominal and perturbed traces), and the nominal registered again on it, so that
χ² before and after share one model: at the search's rays χ² along a direction the lateral offset
partly trades against (a tilt about one axis) is as rough as its signal, and the search stops
short (unit 3 at (3°, 3°) read (2.78°, 1.86°) at 500 000 rays; BENCHMARKS.md, sessions 13–14).
Last, the scale and the relative fluxes are solved again with the least squares corrected for the
traced maps' own Monte Carlo noise (errors in variables: each map's expected Σ w²·variance taken off
the normal matrix): a map traced with few rays per bin looks like the others' noise-wise, which
pulls a fitted flux towards the nominal — LED 2 at 0.5 on V1 read 0.60 ± 0.01 on average at
200 000 model rays, 0.50 after the correction (BENCHMARKS.md). ``setup.template_noise_corrected``
is false where the maps' noise swamps what fixes the fluxes (the corrected matrix not positive
definite) and the plain values are kept.
Uncertainties: the covariance's diagonal, scaled by χ²_red where it exceeds 1.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.calibrate.attribute import BIC_THRESHOLD, CHI2_FLOOR
from cm2optics.calibrate.effects import Parameter
from cm2optics.design import SystemDesign
from cm2optics.design.as_built_illumination import COLLIMATOR_DECENTER_MM, LED_FLUX, LED_TILT_DEG
from cm2optics.errors import UserError

__all__ = [
    "IlluminationCalibration",
    "MeasuredMap",
    "UnitEffect",
    "bin_measured_map",
    "calibrate_illumination",
    "illumination_effects",
    "read_measured_map",
    "tent_deposit",
    "tent_weights",
]

Progress = Callable[[str], None]

#: Registration parameters: global scale, lateral offset of the measured map (mm).
NUISANCE = ("scale", "offset_x_mm", "offset_y_mm")
#: Gauss–Newton iterations of a refit.
ITERATIONS = 6
#: Candidates refitted (Gauss–Newton, the tracer in the loop) each round, the best by the
#: linearised BIC: a large tilt is far from linear, so the linearised ranking alone can prefer a
#: flux change that mimics part of it.
REFITTED_CANDIDATES = 3
#: Least number of bins a map must cover.
MIN_BINS = 30
#: Largest lateral offset of the measured map fitted, mm (used bins keep this much inside the image).
MAX_OFFSET_MM = 0.5
#: Independent model traces (seeds seed + 1 … seed + K) on which a refitted traced candidate must
#: lower the BIC before it is kept (:func:`_held_out_threshold`).
HELD_OUT_TRACES = 8
#: The held-out check's one-sided z: a candidate that does not improve the model passes it with a
#: chance of at most Φ(−3) ≈ 0.13 % (:func:`_held_out_threshold`).
HELD_OUT_Z = 3.0
#: The final refit (polish) of kept traced effects uses the model traced with this many times the
#: rays: the search's χ² along a traded direction (a tilt against the lateral offset) is as rough
#: as its signal at the search's rays (BENCHMARKS.md, session 13).
POLISH_RAYS_FACTOR = 4


@dataclass(frozen=True)
class UnitEffect:
    """An effect of one LED unit: its vocabulary name, parameters and whether it needs re-traces."""

    name: str
    unit: int
    parameters: tuple[Parameter, ...]
    description: str
    traced: bool  # False: linear in the unit's own map (led_flux)

    @property
    def key(self) -> str:
        return f"{self.name}[{self.unit}]"


def _pair_effect(
    name: str, unit: int, names: tuple[str, str], limit: float, step: float, description: str
) -> UnitEffect:
    """A traced effect of two parameters, each within ±limit, finite-difference step ``step``."""
    return UnitEffect(name, unit, tuple(Parameter(n, 0.0, -limit, limit, step) for n in names), description, True)


def illumination_effects(units: int, collimator: bool) -> tuple[UnitEffect, ...]:
    """Every candidate effect of ``units`` LED units (decentres only with a collimator)."""
    low, high = LED_FLUX
    out = []
    for u in range(units):
        out.append(
            UnitEffect(
                "led_flux",
                u,
                (Parameter("flux", 1.0, low, high, 0.02),),
                "the LED emits more or less than the others (binning, ageing, drive current)",
                False,
            )
        )
        out.append(
            _pair_effect(
                "led_tilt",
                u,
                ("tilt_x_deg", "tilt_y_deg"),
                LED_TILT_DEG,
                0.5,
                "the unit is tilted about its LED (its housing seated askew)",
            )
        )
        if collimator:
            out.append(
                _pair_effect(
                    "collimator_decenter",
                    u,
                    ("dx_mm", "dy_mm"),
                    COLLIMATOR_DECENTER_MM,
                    0.05,
                    "the collimator sits off its LED's axis",
                )
            )
    return tuple(out)


# ----------------------------------------------------------------------------- the measured map


def read_measured_map(path: str | Path) -> np.ndarray:
    """A measured illumination map (2-D TIFF, counts) as float64; one clear error for anything else."""
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such map file")
    try:
        image = np.asarray(tifffile.imread(path), dtype=np.float64)
    except Exception as error:  # tifffile raises many kinds for a file that is not a TIFF
        raise UserError(f"{path}: not a readable TIFF ({type(error).__name__}: {error})") from None
    image = np.squeeze(image)
    if image.ndim != 2 or min(image.shape) < 8:
        raise UserError(f"{path}: a map must be one 2-D image of at least 8 × 8 pixels, got shape {image.shape}")
    if not np.all(np.isfinite(image)):
        raise UserError(f"{path}: the map holds NaN or infinite values")
    if image.max() <= 0:
        raise UserError(f"{path}: the map is empty (no value > 0)")
    return image


def tent_weights(centres_mm: np.ndarray, positions_mm: np.ndarray, pitch_mm: float) -> np.ndarray:
    """(centres, positions) weights of the tent kernel, max(0, 1 − |x − c| / pitch), along one axis."""
    return np.maximum(0.0, 1.0 - np.abs(centres_mm[:, None] - positions_mm[None, :]) / pitch_mm)


@dataclass(frozen=True, eq=False)
class MeasuredMap:
    """The measured map and its comparison grid.

    image: (y, x) counts. pixel_mm: its pixel on the sample, mm. bin_mm: the grid's pitch, mm.
    half_mm: grid half-width, mm. rows, cols: (n, h) and (n, w) tent weights of the image's rows
    and columns on the grid's centres. index: (B,) flat index of each used centre in the (n, n)
    grid. pixels: (B,) effective pixels per used centre, (Σw)²/Σw². centres_mm: (B, 2) used
    centres (x, y), mm. values: (B,) kernel-weighted mean counts per pixel, no offset.
    correlation_factor: the lower Cholesky factor of the used centres' noise correlation
    (:func:`tent_correlation`), in scipy's banded lower form.
    """

    image: np.ndarray
    pixel_mm: float
    bin_mm: float
    half_mm: float
    rows: np.ndarray
    cols: np.ndarray
    index: np.ndarray
    pixels: np.ndarray
    centres_mm: np.ndarray
    values: np.ndarray
    correlation_factor: np.ndarray

    @property
    def side(self) -> int:
        return int(round(2 * self.half_mm / self.bin_mm))

    def weighted(self, image: np.ndarray) -> np.ndarray:
        """(B,) kernel-weighted means of ``image`` (y, x) at the used centres."""
        sums = (self.rows @ image @ self.cols.T).ravel()[self.index]
        return sums / np.outer(self.rows.sum(1), self.cols.sum(1)).ravel()[self.index]

    def values_at(self, offset_mm: np.ndarray) -> np.ndarray:
        """(B,) mean counts per pixel with the optical axis at ``offset_mm`` (x, y) in the image
        (the image resampled bilinearly, so that the values change smoothly with the offset)."""
        from scipy.ndimage import shift

        return self.weighted(
            shift(self.image, (-offset_mm[1] / self.pixel_mm, -offset_mm[0] / self.pixel_mm), order=1, mode="nearest")
        )

    def whiten(self, normalised: np.ndarray) -> np.ndarray:
        """(B,) or (B, k) residuals divided by their σ, decorrelated: L⁻¹·x, L the Cholesky factor of
        the centres' correlation, so that noise comes out independent with unit variance."""
        from scipy.linalg import solve_banded

        bandwidth = self.correlation_factor.shape[0] - 1
        return solve_banded((bandwidth, 0), self.correlation_factor, normalised)

    def grid(self, values: np.ndarray) -> np.ndarray:
        """(n, n) image (y, x) of per-centre ``values``, NaN outside the used centres."""
        out = np.full(self.side * self.side, np.nan)
        out[self.index] = values
        return out.reshape(self.side, self.side)


#: Correlation of the noise of two centres one pitch h apart along an axis, for pixels or rays spread
#: evenly under the tent kernel t: ∫t(x)·t(x − h)dx / ∫t(x)²dx = (h/6) / (2h/3); the kernel is the product
#: of one tent per axis, so diagonal neighbours share 1/16, and centres further apart share nothing.
TENT_NEIGHBOUR_CORRELATION = 0.25


def tent_correlation(index: np.ndarray, side: int) -> np.ndarray:
    """The noise correlation of the centres at ``index`` (flat, ascending) of a ``side`` × ``side``
    grid, as the lower Cholesky factor of the (B, B) matrix in scipy's banded lower form
    (row d holds the d-th subdiagonal). The whole grid's correlation is positive definite (its
    eigenvalues are ≥ (1 − 2·¼)² = ¼), so is every subset's."""
    from scipy.linalg import cholesky_banded

    position = np.full(side * side, -1)
    position[index] = np.arange(index.size)
    row, col = np.divmod(index, side)
    pairs = []  # (positions of centres, of their later neighbours at this step, the correlation)
    for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1)):
        inside = (row + dy < side) & (col + dx >= 0) & (col + dx < side)
        later = np.full(index.size, -1)
        later[inside] = position[(row[inside] + dy) * side + col[inside] + dx]
        mine = np.flatnonzero(later >= 0)
        value = TENT_NEIGHBOUR_CORRELATION ** (abs(dy) + abs(dx))
        pairs.append((mine, later[mine], value))
    bandwidth = max([int((j - i).max()) for i, j, _ in pairs if i.size] + [0])
    banded = np.zeros((bandwidth + 1, index.size))
    banded[0] = 1.0
    for i, j, value in pairs:
        banded[j - i, i] = value
    return cholesky_banded(banded, lower=True)


def bin_measured_map(image: np.ndarray, pixel_um: float, bin_mm: float, radius_mm: float) -> MeasuredMap:
    """The comparison grid of ``image`` (y, x; its centre on the axis, ``pixel_um`` µm per pixel
    on the sample): centres of pitch ``bin_mm`` inside the circle of ``radius_mm`` whose kernel
    the image covers whole with :data:`MAX_OFFSET_MM` to spare (room for the fitted offset)."""
    if not (math.isfinite(pixel_um) and pixel_um > 0):
        raise UserError(f"--pixel-um = {pixel_um}: must be a number > 0")
    pixel_mm = pixel_um / 1000.0
    if pixel_mm > bin_mm / 2:
        raise UserError(f"--pixel-um = {pixel_um}: the map's pixels must be at most half a bin ({bin_mm} mm)")
    half = bin_mm * math.ceil(radius_mm / bin_mm)
    n = int(round(2 * half / bin_mm))
    h, w = image.shape
    centres = -half + bin_mm * (np.arange(n) + 0.5)
    rows = tent_weights(centres, (np.arange(h) - (h - 1) / 2) * pixel_mm, bin_mm)
    cols = tent_weights(centres, (np.arange(w) - (w - 1) / 2) * pixel_mm, bin_mm)
    cx, cy = np.meshgrid(centres, centres)
    reach = bin_mm + MAX_OFFSET_MM  # a used centre's kernel and the offset's room lie inside the image
    covered = (np.abs(cx) + reach <= w * pixel_mm / 2) & (np.abs(cy) + reach <= h * pixel_mm / 2)
    used = (covered & (np.hypot(cx, cy) <= radius_mm)).ravel()
    if used.sum() < MIN_BINS:
        raise UserError(
            f"the map ({h} × {w} px at {pixel_um} µm = {w * pixel_mm:.2f} × {h * pixel_mm:.2f} mm) covers "
            f"{int(used.sum())} bins of {bin_mm} mm inside the {2 * radius_mm:g}-mm field with ±{bin_mm + MAX_OFFSET_MM} mm "
            f"to spare: at least {MIN_BINS} needed"
        )
    index = np.flatnonzero(used)
    pixels = np.outer(rows.sum(1) ** 2 / (rows**2).sum(1), cols.sum(1) ** 2 / (cols**2).sum(1)).ravel()[index]
    grid = MeasuredMap(
        image,
        pixel_mm,
        bin_mm,
        half,
        rows,
        cols,
        index,
        pixels,
        np.column_stack([cx.ravel()[index], cy.ravel()[index]]),
        np.empty(0),
        tent_correlation(index, n),
    )
    return dataclasses.replace(grid, values=grid.weighted(image))


# ----------------------------------------------------------------------------- the traced model


def tent_deposit(
    measured: MeasuredMap, points_mm: np.ndarray, group: np.ndarray, groups: int
) -> tuple[np.ndarray, np.ndarray]:
    """(groups, B) sums of the tent weights of ``points_mm`` (N, 2: x, y, mm) at the used centres,
    per ``group`` (N,) of each point, and the sums of the squared weights: each point shares 1
    among its four nearest centres, the same kernel as :meth:`MeasuredMap.weighted` gives pixels."""
    n = measured.side
    u = (points_mm.astype(np.float64) + measured.half_mm) / measured.bin_mm - 0.5  # in centres' index units
    low = np.floor(u).astype(np.int64)
    frac = u - low
    sums = np.zeros((2, groups * n * n))
    for di in (0, 1):
        for dj in (0, 1):
            i, j = low[:, 0] + di, low[:, 1] + dj  # column (x), row (y)
            weight = (frac[:, 0] if di else 1 - frac[:, 0]) * (frac[:, 1] if dj else 1 - frac[:, 1])
            ok = (i >= 0) & (i < n) & (j >= 0) & (j < n)
            flat = group[ok].astype(np.int64) * (n * n) + j[ok] * n + i[ok]
            sums[0] += np.bincount(flat, weights=weight[ok], minlength=sums.shape[1])
            sums[1] += np.bincount(flat, weights=weight[ok] ** 2, minlength=sums.shape[1])
    sums = sums.reshape(2, groups, n * n)[:, :, measured.index]
    return sums[0], sums[1]


#: Traces kept for reuse within a process (sample-plane hits, ≈ 3 MB per million rays traced),
#: least recently used dropped first: maps of the same design, rays and seed (several maps
#: calibrated in one process, the tests' seeds) share the model's traces.
TRACES_KEPT = 64
_TRACES: OrderedDict[tuple[str, int, int, bytes], tuple[np.ndarray, np.ndarray, float]] = OrderedDict()


class TracedMaps:
    """The design's irradiance per LED unit on the measured map's bins, for any unit tilts and
    collimator decentres (traces cached, :data:`TRACES_KEPT`; the same rays every time: common
    random numbers). ``traces``: the traces this instance made (cache hits not counted)."""

    def __init__(self, design: SystemDesign, measured: MeasuredMap, rays: int, seed: int):
        from cm2optics.illumination.compare import setup_from_options
        from cm2optics.illumination.geometry import build_scene, collimator_from_design

        self.setup = setup_from_options(design, rays=rays, seed=seed)
        collimator = collimator_from_design(design) if design.collimator is not None else None
        self.scene = build_scene(design, collimator)
        self.measured = measured
        self._identity = (design.parameter_hash(), rays, seed)
        self.traces = 0

    @property
    def units(self) -> int:
        return self.scene.units

    def _hits(self, geometry: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Sample-plane hits (mm), their units and the power per ray (mW) for ``geometry``
        (units, 4): tilt about x, y (degrees), collimator decentre dx, dy (mm)."""
        from cm2optics.illumination.robustness import UnitError, perturbed_scene
        from cm2optics.illumination.tracer import Status, trace

        key = (*self._identity, np.round(geometry, 9).tobytes())
        if key in _TRACES:
            _TRACES.move_to_end(key)
        else:
            scene = self.scene
            if np.any(geometry != 0):
                offsets = -geometry[:, 2:] if scene.collimator is not None else np.zeros((self.units, 2))
                scene = perturbed_scene(
                    scene, [UnitError(o, t, None) for o, t in zip(offsets, geometry[:, :2], strict=True)]
                )
            record = trace(
                scene, self.setup.source, self.setup.rays, transmission=self.setup.transmission, seed=self.setup.seed
            )
            on = record.status == int(Status.SAMPLE)
            _TRACES[key] = (record.hit_mm[on].astype(np.float32), record.unit[on].astype(np.int8), record.power_mw)
            self.traces += 1
            while len(_TRACES) > TRACES_KEPT:
                _TRACES.popitem(last=False)
        return _TRACES[key]

    def maps(self, geometry: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(units, B) irradiance (mW/mm²) of each unit at the used centres, and its Monte Carlo
        variance ((mW/mm²)²)."""
        hits, unit, power = self._hits(geometry)
        weights, squares = tent_deposit(self.measured, hits, unit, self.units)
        per_ray = power / self.measured.bin_mm**2
        return weights * per_ray, squares * per_ray**2


@dataclass(frozen=True)
class _Slot:
    """One fitted number: its effect (None: registration), parameter and where it sits in the model."""

    effect: UnitEffect | None
    parameter: Parameter
    column: int  # registration: index in NUISANCE; flux: −1; geometry: 0–3 (tilt x, y, dx, dy)


def _nuisance_slots(pixel_mm: float) -> list[_Slot]:
    return [
        _Slot(None, Parameter("scale", 1.0, 0.0, math.inf, 1e-3), 0),
        _Slot(None, Parameter("offset_x_mm", 0.0, -MAX_OFFSET_MM, MAX_OFFSET_MM, pixel_mm), 1),
        _Slot(None, Parameter("offset_y_mm", 0.0, -MAX_OFFSET_MM, MAX_OFFSET_MM, pixel_mm), 2),
    ]


def _effect_slots(effect: UnitEffect) -> list[_Slot]:
    if effect.name == "led_flux":
        return [_Slot(effect, effect.parameters[0], -1)]
    first = 0 if effect.name == "led_tilt" else 2
    return [_Slot(effect, p, first + i) for i, p in enumerate(effect.parameters)]


class _Fit:
    """The model's prediction, noise and χ² for a vector of slot values."""

    def __init__(self, maps: TracedMaps, flux: np.ndarray, geometry: np.ndarray, counts_per_electron: float):
        self.maps = maps
        self.flux0 = flux  # (units,) the design's relative fluxes
        self.geometry0 = geometry  # (units, 4) the design's tilts and decentres
        self.gain = counts_per_electron

    def unpack(self, slots: list[_Slot], theta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        scale, offset = 1.0, np.zeros(2)
        flux, geometry = self.flux0.copy(), self.geometry0.copy()
        for slot, value in zip(slots, theta, strict=True):
            if slot.effect is None:
                if slot.column == 0:
                    scale = value
                else:
                    offset[slot.column - 1] = value
            elif slot.column < 0:
                flux[slot.effect.unit] = value
            else:
                geometry[slot.effect.unit, slot.column] = value
        return scale, offset, flux, geometry

    def predict(self, slots: list[_Slot], theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The predicted counts per pixel in each bin and their variance (shot + Monte Carlo)."""
        scale, _, flux, geometry = self.unpack(slots, theta)
        m, v = self.maps.maps(geometry)
        pred = scale * (flux @ m)
        shot = self.gain * np.maximum(pred, self.gain) / self.maps.measured.pixels
        return pred, shot + scale**2 * ((flux**2) @ v)

    def residual(self, slots: list[_Slot], theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Data at the fitted offset less the prediction, and the noise's variance."""
        _, offset, _, _ = self.unpack(slots, theta)
        pred, var = self.predict(slots, theta)
        return self.maps.measured.values_at(offset) - pred, var

    def chi2(self, slots: list[_Slot], theta: np.ndarray) -> float:
        """Generalised χ²: the residual over its σ, decorrelated (:meth:`MeasuredMap.whiten`)."""
        residual, var = self.residual(slots, theta)
        return float(np.sum(self.maps.measured.whiten(residual / np.sqrt(var)) ** 2))

    def profiled(self, slots: list[_Slot], theta: np.ndarray, template_noise: bool = False) -> tuple[np.ndarray, float]:
        """``theta`` with its linear values — the scale and the free relative fluxes — solved in
        closed form (generalised least squares, the noise of the prediction at ``theta`` and the
        centres' correlation) for its geometry and offset, and the χ² there. ``template_noise``: the
        least squares corrected for the Monte Carlo noise of the traced maps it weights (the
        errors-in-variables moment correction: the normal matrix less each basis map's expected
        noise, Σ w²·variance — whitening leaves it so where σ changes little between neighbouring
        centres, Σⱼ Rᵢⱼ(R⁻¹)ⱼᵢ = 1), which otherwise pulls a relative flux towards the others'
        (BENCHMARKS.md: LED 2 at 0.5 on V1 reads 0.60 ± 0.01 over 16 model seeds at 200 000 rays)."""
        _, offset, flux, geometry = self.unpack(slots, theta)
        maps, variance = self.maps.maps(geometry)
        _, var = self.predict(slots, theta)
        free = [i for i, s in enumerate(slots) if s.effect is not None and s.column < 0]
        free_units = [slots[i].effect.unit for i in free]
        fixed = np.array([u not in free_units for u in range(self.maps.units)])
        basis = [flux[fixed] @ maps[fixed]] if fixed.any() else []
        basis = np.array(basis + [maps[u] for u in free_units])
        weight = 1.0 / np.sqrt(var)
        data = self.maps.measured.values_at(offset)
        a = self.maps.measured.whiten((basis * weight).T).T
        if template_noise:
            noise = [flux[fixed] ** 2 @ variance[fixed]] if fixed.any() else []
            normal = a @ a.T - np.diag(np.array(noise + [variance[u] for u in free_units]) @ weight**2)
            if not np.linalg.eigvalsh(normal).min() > 0:
                return theta, math.nan  # the maps' noise swamps what fixes these fluxes: no correction
            coef = np.linalg.solve(normal, a @ self.maps.measured.whiten(data * weight))
        else:
            coef = np.linalg.lstsq(a.T, self.maps.measured.whiten(data * weight), rcond=None)[0]
        out = theta.copy()
        scale = coef[0] if fixed.any() else theta[0]
        out[0] = scale
        for i, c in zip(free, coef[1:] if fixed.any() else coef, strict=True):
            out[i] = c / scale
        low = np.array([s.parameter.low for s in slots])
        high = np.array([s.parameter.high for s in slots])
        out = np.clip(out, low, high)
        return out, self.chi2(slots, out)

    def jacobian(self, slots: list[_Slot], theta: np.ndarray, central: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(B, k) forward (or central) differences of the model less the data and the residual,
        both over σ and decorrelated (:meth:`MeasuredMap.whiten`): the linear least squares of
        the generalised χ²."""
        residual, var = self.residual(slots, theta)
        jac = np.empty((residual.size, len(slots)))
        for i, slot in enumerate(slots):
            step = np.zeros(len(theta))
            h = slot.parameter.step * (max(abs(theta[i]), 1.0) if slot.column == 0 and slot.effect is None else 1.0)
            step[i] = h
            below = self.residual(slots, theta - step)[0] if central else residual
            jac[:, i] = (below - self.residual(slots, theta + step)[0]) / (2 * h if central else h)
        sigma = np.sqrt(var)
        whiten = self.maps.measured.whiten
        return whiten(jac / sigma[:, None]), whiten(residual / sigma)

    def refine(
        self, slots: list[_Slot], theta: np.ndarray, central: bool = False
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Gauss–Newton from ``theta`` (step halving, bounds; ``central`` differences: no bias
        from the curvature of a traced tilt in where it stops): the values, χ² and covariance."""
        low = np.array([s.parameter.low for s in slots])
        high = np.array([s.parameter.high for s in slots])
        chi2 = self.chi2(slots, theta)
        for _ in range(ITERATIONS):
            a, b = self.jacobian(slots, theta, central)
            delta = np.linalg.lstsq(a, b, rcond=None)[0]
            for shrink in (1.0, 0.5, 0.25, 0.125):
                trial = np.clip(theta + shrink * delta, low, high)
                trial_chi2 = self.chi2(slots, trial)
                if trial_chi2 < chi2:
                    break
            else:
                break
            improved = chi2 - trial_chi2
            theta, chi2 = trial, trial_chi2
            if improved < 1e-4 * chi2 + 1e-6:
                break
        a, _ = self.jacobian(slots, theta, central)
        cov = np.linalg.pinv(a.T @ a)
        return theta, chi2, cov


# ----------------------------------------------------------------------------- attribution


@dataclass(frozen=True)
class IlluminationCalibration:
    """The result: the JSON document, the maps on the comparison grid and the corrected design.

    measured: the data's grid. before, after: (data at the fitted offset, model, noise σ) per
    used bin, counts per pixel, for the nominal and the corrected model (registration fitted).
    """

    document: dict[str, Any]
    measured: MeasuredMap
    before: tuple[np.ndarray, np.ndarray, np.ndarray]
    after: tuple[np.ndarray, np.ndarray, np.ndarray]
    corrected_design: SystemDesign


def _start(fit: _Fit, slots: list[_Slot]) -> np.ndarray:
    """Registration start: the scale that matches the nominal map's total, no offset."""
    theta = np.array([s.parameter.default for s in slots])
    pred, _ = fit.predict(slots, theta)
    theta[0] = float(fit.maps.measured.values.sum() / max(pred.sum(), 1e-300))
    return theta


def _candidate_scores(
    fit: _Fit, slots: list[_Slot], theta: np.ndarray, candidates: list[UnitEffect], penalty: float
) -> list[tuple[float, UnitEffect]]:
    """BIC of each candidate fitted (linearised at ``theta``) beside the slots already free."""
    trial_slots = slots + [s for c in candidates for s in _effect_slots(c)]
    trial_theta = np.concatenate([theta] + [_current(fit, slots, theta, c) for c in candidates])
    a, b = fit.jacobian(trial_slots, trial_theta)
    base = list(range(len(slots)))
    scores = []
    at = len(slots)
    for c in candidates:
        cols = base + list(range(at, at + len(c.parameters)))
        at += len(c.parameters)
        delta = np.linalg.lstsq(a[:, cols], b, rcond=None)[0]
        chi2 = float(np.sum((b - a[:, cols] @ delta) ** 2))
        scores.append((chi2 + penalty * len(cols), c))
    return scores


def _refitted(
    fit: _Fit, slots: list[_Slot], theta: np.ndarray, candidate: UnitEffect, penalty: float
) -> tuple[float, UnitEffect, list[_Slot], tuple[np.ndarray, float, np.ndarray]]:
    """``candidate`` refitted by Gauss–Newton beside the slots already free (all of them free
    again): its BIC, the candidate, the slots and the fit (values, χ², covariance). A traced
    candidate starts from the best (by χ², the scale and free fluxes solved in closed form at
    each point) of its current values and the points half its range away on a 3 × 3 grid: a
    tilt of a few degrees moves a unit's spot too far for one linearisation, and changes the
    power on the sample, which stale linear values would count against it. Central differences:
    a forward difference shares the trace at the current values, and its Monte Carlo noise, with
    the residual (the rays whose fate or place the step changes), which pulls the step back towards
    the current values (a 0.25-mm collimator decentre stalled at its grid start, −0.15 mm)."""
    trial_slots = slots + _effect_slots(candidate)
    current = _current(fit, slots, theta, candidate)
    starts = [current]
    if candidate.traced:
        half = np.array([p.high for p in candidate.parameters]) / 2
        grid = np.stack(np.meshgrid(*[(-1, 0, 1)] * len(current), indexing="ij"), -1).reshape(-1, len(current))
        starts = [np.clip(current + g * half, -2 * half, 2 * half) for g in grid]
    profiled = [fit.profiled(trial_slots, np.concatenate([theta, values])) for values in starts]
    start, _ = min(profiled, key=lambda t: t[1])
    refit = fit.refine(trial_slots, start, central=True)
    return refit[1] + penalty * len(trial_slots), candidate, trial_slots, refit


def _held_out_gain(
    held_out: list[_Fit],
    slots: list[_Slot],
    theta: np.ndarray,
    trial_slots: list[_Slot],
    trial: np.ndarray,
    penalty: float,
) -> list[float]:
    """The BIC drop of a refitted traced candidate on each model traced with independent rays (the
    scale and free fluxes solved again there, the rest as fitted). Its gain on the rays it was fitted
    with includes the model's Monte Carlo noise that the refit and the grid start chose; on independent
    rays a geometry fitted to that noise loses instead."""
    gains = []
    for fit in held_out:
        before = fit.profiled(slots, theta)[1] + penalty * len(slots)
        after = fit.profiled(trial_slots, trial)[1] + penalty * len(trial_slots)
        gains.append(before - after)
    return gains


def _held_out_threshold(dof: int, traces: int) -> float:
    """The least mean BIC drop over ``traces`` held-out traces that keeps a traced candidate:
    ``BIC_THRESHOLD`` or ``HELD_OUT_Z`` standard deviations of that mean under no improvement,
    whichever is larger. On one held-out trace the χ² of the current model and of the candidate
    are each χ² of ``dof`` degrees of freedom (variance 2·dof: the model's Monte Carlo noise
    dominates, the generalised χ² decorrelates the centres); where the candidate's geometry moves
    its unit's rays by more than a bin, the two traces share almost no ray fates or bins and the
    two χ² are independent draws, so their difference varies by 2·2·dof — an upper bound, as
    common rays only correlate them (a 0.15-mm collimator decentre moves its beam ≈ 1.9 mm; the
    measured spread of Δχ² over model seeds ≈ 35 against √(4·207) ≈ 29, BENCHMARKS.md). The
    traces are independent (the data, shared, adds no covariance between them while the model is
    right), so their mean varies by 4·dof / K; a candidate no better than the current model has a
    mean Δχ² ≤ 0 and its ΔBIC lower still, by the penalty: it passes with a chance of at most
    Φ(−``HELD_OUT_Z``) (0.13 % for z = 3, per candidate judged)."""
    return max(BIC_THRESHOLD, HELD_OUT_Z * math.sqrt(4 * dof / traces))


def _current(fit: _Fit, slots: list[_Slot], theta: np.ndarray, effect: UnitEffect) -> np.ndarray:
    """The values ``effect``'s parameters have in the model now."""
    _, _, flux, geometry = fit.unpack(slots, theta)
    if effect.name == "led_flux":
        return np.array([flux[effect.unit]])
    return np.array([geometry[effect.unit, s.column] for s in _effect_slots(effect)])


def _radial_profile(measured: MeasuredMap, values: np.ndarray, width_mm: float) -> list[float | None]:
    """Mean of ``values`` in annuli of ``width_mm`` about the axis (None where no bin falls)."""
    ring = (np.hypot(measured.centres_mm[:, 0], measured.centres_mm[:, 1]) // width_mm).astype(int)
    sums = np.bincount(ring, weights=values)
    counts = np.bincount(ring)
    return [round(float(s / c), 6) if c else None for s, c in zip(sums, counts, strict=True)]


def _unexplained(
    measured: MeasuredMap, residual: np.ndarray, sigma: np.ndarray, design: SystemDesign, chi2_red: float, dof: int
) -> list[dict[str, Any]]:
    """The signature of a residual left above the noise: where its smoothed peak lies, its sign,
    the LED unit on that side and its share of the map's energy. Empty below the noise floor:
    ``CHI2_FLOOR``, or 3 σ of χ²_red's own spread (1 + 3√(2/dof)) where a map has few bins (the
    generalised χ² of a matching model is χ²(dof), dof = bins − fitted values)."""
    if chi2_red <= max(CHI2_FLOOR, 1 + 3 * math.sqrt(2 / dof)):
        return []
    from scipy.ndimage import uniform_filter

    z = np.nan_to_num(measured.grid(residual / sigma))
    weight = measured.grid(np.ones_like(residual))
    smooth = uniform_filter(z, 3) / np.maximum(uniform_filter(np.nan_to_num(weight), 3), 1e-9)
    smooth[np.isnan(weight)] = 0.0
    peak = np.unravel_index(np.argmax(np.abs(smooth)), smooth.shape)
    centres = -measured.half_mm + measured.bin_mm * (np.arange(measured.side) + 0.5)
    x, y = float(centres[peak[1]]), float(centres[peak[0]])
    arr = design.led_array
    azimuths = np.radians(arr.azimuth_deg) + 2 * np.pi * np.arange(arr.count) / arr.count
    side = int(np.argmax(np.cos(azimuths - math.atan2(y, x)))) if math.hypot(x, y) > measured.bin_mm else None
    fraction = float(np.sum(residual**2) / np.sum(measured.values**2))
    where = f"near unit {side}'s side" if side is not None else "at the centre"
    return [
        {
            "lenslets": [],
            "units": [] if side is None else [side],
            "field_mm": [round(x, 3), round(y, 3)],
            "depths_mm": [],
            "energy_fraction": round(fraction, 6),
            "description": (
                f"{'excess' if smooth[peak] > 0 else 'deficit'} of light around ({x:.2f}, {y:.2f}) mm, {where}; "
                f"reduced χ² {chi2_red:.3g} after the effects: no illumination effect of the library "
                "(led_flux, led_tilt, collimator_decenter) explains it"
            ),
        }
    ]


def _effect_records(slots: list[_Slot], theta: np.ndarray, cov: np.ndarray, inflate: float) -> list[dict[str, Any]]:
    records: dict[str, dict[str, Any]] = {}
    for i, slot in enumerate(slots):
        if slot.effect is None:
            continue
        record = records.setdefault(
            slot.effect.key,
            {"name": slot.effect.name, "unit": slot.effect.unit, "parameters": {}, "uncertainties": {}},
        )
        record["parameters"][slot.parameter.name] = round(float(theta[i]), 6)
        record["uncertainties"][slot.parameter.name] = round(float(math.sqrt(max(cov[i, i], 0.0) * inflate)), 6)
    return list(records.values())


def _corrected(design: SystemDesign, flux: np.ndarray, geometry: np.ndarray) -> SystemDesign:
    """``design`` with the fitted fluxes, tilts and decentres as its ``illumination_as_built``."""
    low, high = LED_FLUX
    return design.with_changes(
        {
            "illumination_as_built.led_flux": [round(float(np.clip(f, low, high)), 4) for f in flux],
            "illumination_as_built.led_tilt_deg": [[round(float(v), 4) for v in g[:2]] for g in geometry],
            "illumination_as_built.collimator_decenter_mm": (
                [[round(float(v), 5) for v in g[2:]] for g in geometry] if design.collimator is not None else []
            ),
        }
    )


def _registration(slots: list[_Slot], theta: np.ndarray, cov: np.ndarray, inflate: float) -> dict[str, float]:
    out = {}
    for i, name in enumerate(NUISANCE):
        out[name] = round(float(theta[i]), 6)
        out[f"{name}_stderr"] = round(float(math.sqrt(max(cov[i, i], 0.0) * inflate)), 6)
    return out


def _nmse(data: np.ndarray, model: np.ndarray) -> float:
    return round(float(np.sum((data - model) ** 2) / np.sum(data**2)), 8)


def _cv(values: np.ndarray) -> float:
    return round(float(values.std() / values.mean()), 6)


def calibrate_illumination(
    image: np.ndarray,
    pixel_um: float,
    design: SystemDesign,
    *,
    bin_mm: float = 0.5,
    rays: int = 400_000,
    seed: int = 0,
    counts_per_electron: float = 1.0,
    max_effects: int = 4,
    effect_names: tuple[str, ...] | None = None,
    label: str = "map",
    progress: Progress | None = None,
    polish_rays: int | None = None,
) -> IlluminationCalibration:
    """Register the design's traced irradiance map to a measured one (``image``, counts, ``pixel_um``
    µm per pixel on the sample), name the illumination effects the residual asks for (only those
    in ``effect_names`` if given) and return the document, the maps and the corrected design.
    ``label`` names the map in the document (its file). ``polish_rays``: rays of the final refit
    when a traced effect is kept (default ``POLISH_RAYS_FACTOR`` × ``rays``; ≤ ``rays``: none)."""
    say = progress or (lambda message: None)
    if not (math.isfinite(counts_per_electron) and counts_per_electron > 0):
        raise UserError(f"--counts-per-electron = {counts_per_electron}: must be a number > 0")
    if not 0 < bin_mm <= design.volume.field_mm / 4:
        raise UserError(f"--bin-mm = {bin_mm}: must lie within 0–{design.volume.field_mm / 4} mm")
    if rays < 1000:
        raise UserError(f"--rays = {rays}: must be ≥ 1000")
    polish_rays = POLISH_RAYS_FACTOR * rays if polish_rays is None else polish_rays
    if polish_rays < 0:
        raise UserError(f"--polish-rays = {polish_rays}: must be ≥ 0 (0: no final refit at more rays)")
    measured = bin_measured_map(image, pixel_um, bin_mm, design.volume.field_mm / 2)
    say(f"{measured.values.size} bins of {bin_mm} mm; tracing {design.name} with {rays} rays")
    maps = TracedMaps(design, measured, rays, seed)
    traced = [maps]  # every model traced (its traces counted in the document)
    built = design.illumination_as_built
    units = maps.units
    fit = _Fit(
        maps,
        np.array([built.flux(u) for u in range(units)]),
        np.array([[*built.tilt_deg(u), *built.decenter_mm(u)] for u in range(units)]),
        counts_per_electron,
    )
    slots = _nuisance_slots(measured.pixel_mm)
    theta, chi2, cov = fit.refine(slots, _start(fit, slots))
    registration = slots, theta
    n = measured.values.size
    penalty = math.log(n)
    before, var_before = fit.predict(slots, theta)
    data_before = measured.values_at(fit.unpack(slots, theta)[1])
    chi2_before = chi2 / (n - len(slots))
    steps = [{"effect": None, "chi2": round(chi2_before, 5), "bic": round(chi2 + penalty * len(slots), 3)}]
    candidates = [
        e
        for e in illumination_effects(units, maps.scene.collimator is not None)
        if effect_names is None or e.name in effect_names
    ]
    kept: list[UnitEffect] = []
    held_out: list[_Fit] = []  # the model traced with other rays (HELD_OUT_TRACES seeds), made when first needed
    while len(kept) < max_effects:
        remaining = [c for c in candidates if c not in kept]
        if not remaining:
            break
        say(f"reduced χ² {chi2 / (n - len(slots)):.3g}: fitting {len(remaining)} candidates")
        bic_now = chi2 + penalty * len(slots)
        scores = sorted(_candidate_scores(fit, slots, theta, remaining, penalty), key=lambda t: t[0])
        finalists = [c for bic, c in scores[:REFITTED_CANDIDATES] if bic_now - bic >= BIC_THRESHOLD]
        if not finalists:
            break
        chosen = None
        for bic, best, trial_slots, refit in sorted(
            (_refitted(fit, slots, theta, c, penalty) for c in finalists), key=lambda t: t[0]
        ):
            if bic_now - bic < BIC_THRESHOLD:
                break
            confirmation: dict[str, Any] = {}
            if best.traced:
                if not held_out:
                    traced += [TracedMaps(design, measured, rays, seed + k) for k in range(1, HELD_OUT_TRACES + 1)]
                    held_out = [_Fit(m, fit.flux0, fit.geometry0, fit.gain) for m in traced[-HELD_OUT_TRACES:]]
                gains = _held_out_gain(held_out, slots, theta, trial_slots, refit[0], penalty)
                needed = _held_out_threshold(n - len(trial_slots), len(gains))
                confirmation = {
                    "held_out_delta_bic": round(float(np.mean(gains)), 3),
                    "held_out_threshold": round(needed, 3),
                    "held_out_each": [round(g, 3) for g in gains],
                }
                if np.mean(gains) < needed:
                    steps.append({"effect": best.key, "rejected": "held-out traces", **confirmation})
                    say(
                        f"{best.key} not confirmed on {len(gains)} independent traces "
                        f"(mean ΔBIC {np.mean(gains):.3g} < {needed:.3g})"
                    )
                    continue
            chosen = bic, best, trial_slots, refit, confirmation
            break
        if chosen is None:
            break
        bic, best, trial_slots, (trial, trial_chi2, trial_cov), confirmation = chosen
        slots, theta, chi2, cov = trial_slots, trial, trial_chi2, trial_cov
        kept.append(best)
        steps.append(
            {"effect": best.key, "chi2": round(chi2 / (n - len(slots)), 5), "bic": round(bic, 3), **confirmation}
        )
        say(f"kept {best.key}: reduced χ² {chi2 / (n - len(slots)):.3g}")
    if polish_rays > rays and any(e.traced for e in kept):
        # The kept values refitted jointly (central differences) on the model traced with more rays,
        # and the nominal registered again on it, so that before and after share one model's noise.
        say(f"final refit of {', '.join(e.key for e in kept)} with {polish_rays} rays")
        traced.append(TracedMaps(design, measured, polish_rays, seed))
        fit = _Fit(traced[-1], fit.flux0, fit.geometry0, fit.gain)
        theta, chi2, cov = fit.refine(slots, theta, central=True)
        nominal, nominal_chi2, _ = fit.refine(*registration)
        before, var_before = fit.predict(registration[0], nominal)
        data_before = measured.values_at(fit.unpack(registration[0], nominal)[1])
        chi2_before = nominal_chi2 / (n - len(registration[0]))
        steps.append(
            {
                "effect": "final refit",
                "rays": polish_rays,
                "chi2": round(chi2 / (n - len(slots)), 5),
                "bic": round(chi2 + penalty * len(slots), 3),
                "chi2_nominal": round(chi2_before, 5),
            }
        )
        say(f"final refit: reduced χ² {chi2 / (n - len(slots)):.3g} (nominal {chi2_before:.3g})")
    corrected, corrected_chi2 = fit.profiled(slots, theta, template_noise=True)
    if math.isfinite(corrected_chi2):
        theta, chi2 = corrected, corrected_chi2
    after, var_after = fit.predict(slots, theta)
    chi2_after = chi2 / (n - len(slots))
    inflate = max(chi2_after, 1.0)
    _, offset, flux, geometry = fit.unpack(slots, theta)
    data = measured.values_at(offset)
    ring = 2 * bin_mm
    document = {
        "design": design.name,
        "parameter_hash": design.parameter_hash(),
        "map": label,
        "effects": _effect_records(slots, theta, cov, inflate),
        "nmse_before": _nmse(data_before, before),
        "nmse_after": _nmse(data, after),
        "chi2_before": round(chi2_before, 5),
        "chi2_after": round(chi2_after, 5),
        "unexplained": _unexplained(measured, data - after, np.sqrt(var_after), design, chi2_after, n - len(slots)),
        "registration": _registration(slots, theta, cov, inflate),
        "steps": steps,
        "uniformity_cv": {
            "data": _cv(data),
            "data_noise": round(float(np.sqrt(np.mean(counts_per_electron * data / measured.pixels)) / data.mean()), 6),
            "model_before": _cv(before),
            "model_after": _cv(after),
        },
        "radial_profile": {
            "ring_mm": ring,
            "radius_mm": [round(ring * (i + 0.5), 4) for i in range(len(_radial_profile(measured, data, ring)))],
            "data": _radial_profile(measured, data, ring),
            "data_before": _radial_profile(measured, data_before, ring),
            "model_before": _radial_profile(measured, before, ring),
            "model_after": _radial_profile(measured, after, ring),
        },
        "noise_model": (
            f"shot noise, {counts_per_electron:g} counts per electron, plus the model's Monte Carlo variance; "
            f"neighbouring centres correlated by the tent kernel (1/{1 / TENT_NEIGHBOUR_CORRELATION:g} along an axis, "
            f"1/{1 / TENT_NEIGHBOUR_CORRELATION**2:g} diagonally): generalised χ²"
        ),
        "setup": {
            "pixel_um": pixel_um,
            "map_shape": list(image.shape),
            "bins": n,
            "bin_mm": bin_mm,
            "rays": rays,
            "seed": seed,
            "traces": sum(m.traces for m in traced),
            "held_out_traces": len(held_out),
            "polish_rays": polish_rays if any(e.traced for e in kept) and polish_rays > rays else None,
            "template_noise_corrected": math.isfinite(corrected_chi2),
            "candidates": sorted({c.name for c in candidates}),
        },
    }
    return IlluminationCalibration(
        document,
        measured,
        (data_before, before, np.sqrt(var_before)),
        (data, after, np.sqrt(var_after)),
        _corrected(design, flux, geometry),
    )
