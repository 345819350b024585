"""A data-driven low-rank correction of the model's foci: the hybrid calibration of the paper's
conclusion, for a residual no physical effect explains. It is *not* physical and says so.

Like the 3D-LSV model, which writes every focus as a few basis terms whose weights vary over the
object, the correction adds ``rank`` extra terms to every model focus m_ij (lenslet j, position
r_i):

    m_ij  +=  Σ_k c_k(j, r_i) · (K_k ∗ m_ij)

K_k small convolution kernels (2·:data:`KERNEL_HALF_PX` + 1 px square) shared by all foci, acting
on the model's own sampled focus — so a focus ≈ 1 px wide keeps its sub-pixel phase, which a
pattern cut around the nearest pixel would not — and c_k(j, r) per lenslet a smooth function of
the position: a Gaussian-kernel ridge regression over (x, y, z) of its fitted weights (about
their mean, or about zero), so that positions not in the fit (the rest of the grid, the LSV
model's interpolation points) get a correction. Its length scales (lateral and depth, each one of
:data:`KERNEL_STEPS` grid steps) and whether it is centred on the mean are chosen by the
regression's closed-form leave-one-out error over the fit's positions: a ghost present at every
position wants the mean and long scales, a loss confined to a few source positions (a scratch on
a filter, seen through one lenslet from a small part of the field) wants short lateral scales
and no mean, which would spread the loss over positions that do not have it. A delta
kernel is a change of the focus's energy, a displaced blurred one a ghost, a wide one a halo.

The kernels and weights are fitted to the residual patches (2·:data:`PATCH_HALF_PX` + 1 px around
each model focus, each weighted by 1/√energy, its shot noise) by alternating least squares
(kernels given the weights, weights given the kernels; the first term's weights start at 1, the
others' at reproducible random values), the kernels ridge-regularised.

:func:`held_out_error` measures what it is worth on positions *held out of its fit*: the used
positions are split into :data:`FOLDS` folds (every FOLDS-th position), each fold's images are
corrected by the correction fitted on the others, and their NMSE and χ² are reported before and
after, with the NMSE a perfect model would leave (the noise model's variance).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from cm2optics.calibrate.features import focus_patches
from cm2optics.calibrate.residual import ResidualAnalysis
from cm2optics.formats.atomic import write_atomic

__all__ = ["PATCH_HALF_PX", "LowRankCorrection", "fit_correction", "held_out_error"]

#: Half-size of the correction's kernels, px (a ghost farther than this from its focus is missed).
KERNEL_HALF_PX = 7
#: Half-size of the patch around each focus the correction is fitted on and added to, px.
PATCH_HALF_PX = 12
#: Foci handled at once when their shifted copies are formed (memory: 1.1 MB each at the defaults).
CHUNK = 64
#: Kernel length scales of the weights' regression over positions tried, in grid steps of an axis.
KERNEL_STEPS = (0.5, 1.0, 1.5, 3.0)
#: Ridge of that regression, relative to the kernel's diagonal (1).
RIDGE = 0.1
#: Ridge on the convolution kernels, relative to the mean diagonal of their normal matrix.
KERNEL_RIDGE = 1e-2
#: Alternating least-squares rounds.
ROUNDS = 8
#: Foci dimmer than this share of their image's brightest take no part (their patches are noise).
BRIGHT_SHARE = 0.05
#: Foci the fit uses at most (the images spread over the scan): their normal matrices take
#: 0.2 MB each at the defaults.
MAX_FOCI = 1500
#: Folds of the held-out check.
FOLDS = 6
#: What the report and the saved correction say of it.
LABEL = "non-physical: a data-driven low-rank correction fitted to the residual, not a physical effect"


@dataclass(frozen=True)
class LowRankCorrection:
    """Extra low-rank terms on every focus (module docstring).

    kernels: (K, s, s) convolution kernels. positions_mm: (M, 3) the fit's positions.
    coefficients: (M, J, K) fitted weights, valid where ``fitted`` (M, J). scale_mm: (3,) length
    scales of the weights' regression (inf: an axis the fit does not vary along). centred: ()
    bool, whether the regression is about each lenslet's mean weights (else about zero).
    explained_share: (K,) share of the fitted residual's weighted energy each term removes.
    """

    kernels: np.ndarray
    positions_mm: np.ndarray
    coefficients: np.ndarray
    fitted: np.ndarray
    scale_mm: np.ndarray
    explained_share: np.ndarray
    centred: np.ndarray = np.True_
    physical: bool = False

    def weights(self, positions_mm: np.ndarray) -> np.ndarray:
        """(N, J, K) the terms' weights at ``positions_mm`` (N, 3), per lenslet."""
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        out = np.zeros((len(positions), self.coefficients.shape[1], len(self.kernels)))
        for j in range(self.coefficients.shape[1]):
            rows = self.fitted[:, j]
            if not rows.any():
                continue
            known = self.coefficients[rows, j]
            mean = known.mean(axis=0) if bool(self.centred) else np.zeros(known.shape[1])
            gram = _kernel(self.positions_mm[rows], self.positions_mm[rows], self.scale_mm)
            dual = np.linalg.solve(gram + RIDGE * np.eye(len(gram)), known - mean)
            out[:, j] = mean + _kernel(positions, self.positions_mm[rows], self.scale_mm) @ dual
        return out

    def images(
        self, model_signal: np.ndarray, centres_px: np.ndarray, positions_mm: np.ndarray, half: int = PATCH_HALF_PX
    ) -> np.ndarray:
        """(N, y, x) counts to add to the model's images ``model_signal`` (counts above dark)
        whose foci sit at ``centres_px`` (N, J, 2), at ``positions_mm`` (N, 3)."""
        wide, inside = focus_patches(model_signal, centres_px, half + KERNEL_HALF_PX)
        weights = self.weights(positions_mm)
        out = np.zeros(model_signal.shape, np.float64)
        centre = np.rint(np.nan_to_num(centres_px)).astype(int)
        kernel = np.einsum("njk,ku->nju", weights, self.kernels.reshape(len(self.kernels), -1))
        for i, j in zip(*np.nonzero(inside), strict=True):
            term = kernel[i, j] @ _shifts(wide[i, j][None], half)[0]
            r, c = centre[i, j]
            out[i, r - half : r + half + 1, c - half : c + half + 1] += term.reshape(2 * half + 1, -1)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "physical": self.physical,
            "label": LABEL,
            "rank": len(self.kernels),
            "kernel_px": int(self.kernels.shape[-1]),
            "fit_positions": int(len(self.positions_mm)),
            "explained_share": [round(float(s), 4) for s in self.explained_share],
            "weights_scale_mm": [None if not np.isfinite(s) else round(float(s), 4) for s in self.scale_mm],
            "weights_centred": bool(self.centred),
        }

    def save(self, path: str | Path) -> Path:
        """Write the correction as ``.npz`` (arrays, and its :meth:`to_dict` as JSON under
        ``metadata``, which says ``physical: false``), atomically."""
        arrays = {name: getattr(self, name) for name in ARRAYS}

        def write(target: Path) -> None:
            with open(target, "wb") as f:
                np.savez(f, metadata=np.array(json.dumps(self.to_dict())), **arrays)

        return write_atomic(Path(path), write)

    @classmethod
    def load(cls, path: str | Path) -> LowRankCorrection:
        """A correction :meth:`save` wrote."""
        with np.load(path) as f:
            metadata = json.loads(str(f["metadata"]))
            return cls(**{name: f[name] for name in ARRAYS}, physical=bool(metadata["physical"]))


#: The arrays a saved correction holds.
ARRAYS = ("kernels", "positions_mm", "coefficients", "fitted", "scale_mm", "explained_share", "centred")


def _kernel(a: np.ndarray, b: np.ndarray, scale_mm: np.ndarray) -> np.ndarray:
    """Gaussian kernel (len(a), len(b)) with per-axis length scales (inf: axis ignored)."""
    d = (a[:, None, :] - b[None, :, :]) / scale_mm
    return np.exp(-0.5 * np.sum(d**2, axis=-1))


def _grid_steps_mm(positions_mm: np.ndarray) -> np.ndarray:
    """(3,) the median step between distinct values of each axis (inf for an axis with one value)."""
    out = np.full(3, np.inf)
    for axis in range(3):
        values = np.unique(np.round(positions_mm[:, axis], 6))
        if len(values) > 1:
            out[axis] = float(np.median(np.diff(values)))
    return out


def _leave_one_out_error(
    positions_mm: np.ndarray, coefficients: np.ndarray, fitted: np.ndarray, scale_mm: np.ndarray, centred: bool
) -> float:
    """Sum over lenslets, terms and positions of the squared error of each fitted weight predicted
    by the regression of the others (closed form of a linear smoother: (y − ŷ)ᵢ / (1 − Hᵢᵢ))."""
    total = 0.0
    for j in range(coefficients.shape[1]):
        rows = fitted[:, j]
        n = int(rows.sum())
        if n < 3:
            continue
        gram = _kernel(positions_mm[rows], positions_mm[rows], scale_mm)
        hat = gram @ np.linalg.inv(gram + RIDGE * np.eye(n))
        if centred:  # ŷ = m + A (y − m), m the mean: H = C + A (I − C), C = 11ᵀ/n
            hat = 1.0 / n + hat - hat.mean(axis=1, keepdims=True)
        y = coefficients[rows, j]
        leave = np.maximum(1.0 - np.diag(hat), 1e-6)
        total += float(np.sum(((y - hat @ y) / leave[:, None]) ** 2))
    return total


def _regression(positions_mm: np.ndarray, coefficients: np.ndarray, fitted: np.ndarray) -> tuple[np.ndarray, bool]:
    """The weights' regression with the least leave-one-out error: length scales (lateral x and y
    together, depth alone; :data:`KERNEL_STEPS` grid steps each) and whether it is centred."""
    steps = _grid_steps_mm(positions_mm)
    best = (math.inf, steps * KERNEL_STEPS[-1], True)
    for lateral in KERNEL_STEPS:
        for depth in KERNEL_STEPS:
            scale = steps * np.array([lateral, lateral, depth])
            for centred in (True, False):
                error = _leave_one_out_error(positions_mm, coefficients, fitted, scale, centred)
                if error < best[0]:
                    best = (error, scale, centred)
    return best[1], best[2]


@dataclass(frozen=True)
class _Foci:
    """The fit's material for the foci that take part (``usable`` (N, J)), F of them in that
    order: residual patches (F, P) and wide model patches (F, w', w'), each times its weight
    1/√energy (shot noise ∝ √energy), and the normal matrices (F, U, U) and moments (F, U) of
    their kernel fits."""

    usable: np.ndarray
    residual: np.ndarray
    wide: np.ndarray
    gram: np.ndarray
    moment: np.ndarray
    half: int


def _foci(analysis: ResidualAnalysis, half: int) -> _Foci:
    model_signal = analysis.model_counts - analysis.registration.dark_level
    centres = analysis.model.centroid_px
    residual, inside = focus_patches(analysis.residual_counts, centres, half)
    wide, inside_wide = focus_patches(model_signal, centres, half + KERNEL_HALF_PX)
    model = wide[..., KERNEL_HALF_PX:-KERNEL_HALF_PX, KERNEL_HALF_PX:-KERNEL_HALF_PX]
    energy = model.sum(axis=(-2, -1))
    brightest = np.max(np.where(inside_wide, energy, 0.0), axis=1, keepdims=True)
    usable = analysis.used[:, None] & inside & inside_wide & (energy > BRIGHT_SHARE * brightest)
    images = np.flatnonzero(usable.any(axis=1))
    if usable.sum() > MAX_FOCI:  # every k-th image, so that the fit spans the scan
        step = int(np.ceil(usable.sum() / MAX_FOCI))
        usable[np.setdiff1d(images, images[::step])] = False
    scale = 1.0 / np.sqrt(energy[usable])
    targets = residual[usable].reshape(int(usable.sum()), -1) * scale[:, None]
    wide = wide[usable] * scale[:, None, None]
    size = (2 * KERNEL_HALF_PX + 1) ** 2
    gram = np.empty((len(wide), size, size), np.float32)
    moment = np.empty((len(wide), size))
    for start in range(0, len(wide), CHUNK):
        part = slice(start, start + CHUNK)
        shifts = _shifts(wide[part], half)  # (chunk, U, P)
        gram[part] = np.einsum("fup,fvp->fuv", shifts, shifts)
        moment[part] = np.einsum("fup,fp->fu", shifts, targets[part])
    return _Foci(usable, targets, wide, gram, moment, half)


def _shifts(wide: np.ndarray, half: int) -> np.ndarray:
    """(F, U, P) the model patches (2·half + 1)² px shifted by every kernel offset: offset u =
    (a, b) is the patch taken (a, b) px into the wider patch ``wide`` (F, w', w') (a view)."""
    width = 2 * half + 1
    view = sliding_window_view(wide, (width, width), axis=(1, 2))  # (F, s, s, w, w)
    return view.reshape(len(wide), -1, width * width)


def _fit(foci: _Foci, keep: np.ndarray, positions_mm: np.ndarray, rank: int) -> LowRankCorrection:
    """The correction fitted on the foci ``keep`` (N, J; a subset of ``foci.usable``) by
    alternating least squares."""
    chosen = keep[foci.usable]
    gram, moment, targets = foci.gram[chosen], foci.moment[chosen], foci.residual[chosen]
    wide = foci.wide[chosen]
    count, size = moment.shape
    ridge = KERNEL_RIDGE * float(np.trace(gram.sum(axis=0, dtype=np.float64))) / (size * count)
    weights = np.random.default_rng(0).standard_normal((count, rank))  # distinct starts, reproducible
    weights[:, 0] = 1.0
    for _ in range(ROUNDS):
        pairs = (weights[:, :, None] * weights[:, None, :]).reshape(count, -1)  # (F, K²)
        blocks = (pairs.T.astype(np.float32) @ gram.reshape(count, -1)).reshape(rank, rank, size, size)
        normal = blocks.transpose(0, 2, 1, 3).reshape(rank * size, rank * size).astype(np.float64)
        normal += ridge * np.eye(rank * size)
        right = (weights[:, :, None] * moment[:, None, :]).sum(axis=0).ravel()
        kernels = np.linalg.solve(normal, right).reshape(rank, size)
        norms = np.linalg.norm(kernels, axis=1)
        kernels = kernels / np.where(norms > 0, norms, 1.0)[:, None]
        columns = _columns(wide, kernels, foci.half)
        weights = _weights(columns, targets)
    columns = _columns(wide, kernels, foci.half)
    removed = np.sum((columns * weights[:, None, :]) ** 2, axis=(0, 1))
    coefficients = np.zeros(keep.shape + (rank,))
    coefficients[keep] = weights
    images = keep.any(axis=1)
    side = 2 * KERNEL_HALF_PX + 1
    fit_positions = np.asarray(positions_mm, float)[images]
    scale, centred = _regression(fit_positions, coefficients[images], keep[images])
    return LowRankCorrection(
        kernels=kernels.reshape(rank, side, side),
        positions_mm=fit_positions,
        coefficients=coefficients[images],
        fitted=keep[images],
        scale_mm=scale,
        explained_share=removed / max(float(np.sum(targets**2)), 1e-30),
        centred=np.bool_(centred),
    )


def _columns(wide: np.ndarray, kernels: np.ndarray, half: int) -> np.ndarray:
    """(F, P, K) every model patch (the centre of ``wide`` (F, w', w')) convolved with every kernel (K, U)."""
    out = np.empty((len(wide), (2 * half + 1) ** 2, len(kernels)))
    for start in range(0, len(wide), CHUNK):
        part = slice(start, start + CHUNK)
        out[part] = np.einsum("fup,ku->fpk", _shifts(wide[part], half), kernels)
    return out


def _weights(columns: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(F, K) least-squares weights of the columns (F, P, K) for the targets (F, P), each focus
    alone (a column that is all zero gets weight 0)."""
    normal = np.einsum("fpk,fpl->fkl", columns, columns)
    right = np.einsum("fpk,fp->fk", columns, targets)
    tiny = 1e-12 * np.maximum(np.trace(normal, axis1=1, axis2=2), 1e-30)
    normal += tiny[:, None, None] * np.eye(columns.shape[-1])
    return np.linalg.solve(normal, right[..., None])[..., 0]


def fit_correction(analysis: ResidualAnalysis, rank: int = 2, half: int = PATCH_HALF_PX) -> LowRankCorrection:
    """The correction fitted to every used image of ``analysis`` (the residual after the
    physical effects)."""
    foci = _foci(analysis, half)
    if not foci.usable.any():
        raise ValueError("no focus bright enough to fit a correction to")
    return _fit(foci, foci.usable, analysis.positions_mm, rank)


def held_out_error(analysis: ResidualAnalysis, rank: int = 2, half: int = PATCH_HALF_PX) -> dict[str, Any]:
    """NMSE and χ² of the used images before and after the correction fitted without them
    (:data:`FOLDS` folds), summed over those images, with the NMSE a perfect model would leave
    (``nmse_noise_floor``: the noise model's variance over the signal's energy)."""
    foci = _foci(analysis, half)
    model_signal = analysis.model_counts - analysis.registration.dark_level
    signal = analysis.residual_counts + model_signal
    variance = analysis.noise.variance(model_signal)
    images = np.flatnonzero(foci.usable.any(axis=1))
    folds = min(FOLDS, len(images))
    before = after = norm = floor = 0.0
    chi2_before, chi2_after = [], []
    for fold in range(folds):
        held = images[fold::folds]
        keep = foci.usable.copy()
        keep[held] = False
        if not keep.any():
            continue
        correction = _fit(foci, keep, analysis.positions_mm, rank)
        added = correction.images(
            model_signal[held], analysis.model.centroid_px[held], analysis.positions_mm[held], half
        )
        for k, i in enumerate(held):
            r0 = analysis.residual_counts[i].astype(np.float64)
            r1 = r0 - added[k]
            before += float(np.sum(r0**2))
            after += float(np.sum(r1**2))
            norm += float(np.sum(signal[i].astype(np.float64) ** 2))
            floor += float(np.sum(variance[i]))
            chi2_before.append(float(np.mean(r0**2 / variance[i])))
            chi2_after.append(float(np.mean(r1**2 / variance[i])))
    return {
        "method": f"{folds}-fold: each image corrected by the correction fitted on the other folds' positions",
        "images": int(len(chi2_before)),
        "nmse_before": round(before / max(norm, 1e-30), 6),
        "nmse_after": round(after / max(norm, 1e-30), 6),
        "nmse_noise_floor": round(floor / max(norm, 1e-30), 6),
        "chi2_before": round(float(np.mean(chi2_before)), 4) if chi2_before else None,
        "chi2_after": round(float(np.mean(chi2_after)), 4) if chi2_after else None,
    }
