"""A data-driven low-rank correction of the model's foci: the hybrid calibration of the paper's
conclusion, for a residual no physical effect explains. It is *not* physical and says so.

Like the 3D-LSV model, which writes every focus as a few basis patterns with weights that vary
over the object, the correction adds ``rank`` extra patterns to every focus:

    focus_ij  +=  e_ij · Σ_k c_k(j, r_i) · B_k

e_ij the model focus's energy (lenslet j, position r_i), B_k (w × w px) patterns centred on the
focus (the leading right singular vectors of the residual patches relative to their foci's
energy, each weighted by √e_ij, the shot-noise SNR), c_k(j, r) per lenslet a smooth function of
the position: the mean of its fitted coefficients plus a Gaussian-kernel ridge regression over
(x, y, z) with length scales of :data:`KERNEL_STEPS` grid steps per axis (so that positions not
in the fit — the rest of the grid, the LSV model's interpolation points — get a correction).

:func:`held_out_error` measures what it is worth on positions *held out of its fit*: each used
position is predicted by the correction fitted on all the others (leave-one-out), and the NMSE
and χ² of those images are reported before and after.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.calibrate.features import focus_patches
from cm2optics.calibrate.residual import ResidualAnalysis
from cm2optics.calibrate.unexplained import PATCH_HALF_PX
from cm2optics.formats.atomic import write_atomic

__all__ = ["LowRankCorrection", "fit_correction", "held_out_error"]

#: Kernel length scale, in grid steps of each axis.
KERNEL_STEPS = 1.5
#: Ridge of the kernel regression, relative to the kernel's diagonal (1).
RIDGE = 0.1
#: Foci dimmer than this share of their image's brightest take no part (their patches are noise).
BRIGHT_SHARE = 0.05
#: What the report and the model's metadata say of it.
LABEL = "non-physical: a data-driven low-rank correction fitted to the residual, not a physical effect"


@dataclass(frozen=True)
class LowRankCorrection:
    """Extra low-rank terms on every focus (module docstring).

    basis: (K, w, w) patterns per unit focus energy. positions_mm: (M, 3) the fit's positions.
    coefficients: (M, J, K) fitted weights, valid where ``fitted`` (M, J). scale_mm: (3,) kernel
    length scales (inf: an axis the fit does not vary along). singular_share: (K,) share of the
    weighted residual's energy each pattern holds.
    """

    basis: np.ndarray
    positions_mm: np.ndarray
    coefficients: np.ndarray
    fitted: np.ndarray
    scale_mm: np.ndarray
    singular_share: np.ndarray
    physical: bool = False

    @property
    def half_px(self) -> int:
        return self.basis.shape[-1] // 2

    def weights(self, positions_mm: np.ndarray) -> np.ndarray:
        """(N, J, K) the patterns' weights at ``positions_mm`` (N, 3), per lenslet."""
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        out = np.zeros((len(positions), self.coefficients.shape[1], len(self.basis)))
        for j in range(self.coefficients.shape[1]):
            rows = self.fitted[:, j]
            if not rows.any():
                continue
            known = self.coefficients[rows, j]
            mean = known.mean(axis=0)
            gram = _kernel(self.positions_mm[rows], self.positions_mm[rows], self.scale_mm)
            dual = np.linalg.solve(gram + RIDGE * np.eye(len(gram)), known - mean)
            out[:, j] = mean + _kernel(positions, self.positions_mm[rows], self.scale_mm) @ dual
        return out

    def images(self, model_signal: np.ndarray, centres_px: np.ndarray, positions_mm: np.ndarray) -> np.ndarray:
        """(N, y, x) counts to add to the model's images ``model_signal`` (counts above dark) whose
        foci sit at ``centres_px`` (N, J, 2), at ``positions_mm`` (N, 3)."""
        half = self.half_px
        patches, inside = focus_patches(model_signal, centres_px, half)
        energy = patches.sum(axis=(-2, -1))
        terms = np.einsum("njk,kab->njab", self.weights(positions_mm), self.basis) * energy[..., None, None]
        out = np.zeros_like(model_signal, dtype=np.float64)
        centre = np.rint(np.nan_to_num(centres_px)).astype(int)
        offsets = np.arange(-half, half + 1)
        for i, j in zip(*np.nonzero(inside), strict=True):
            r, c = centre[i, j]
            out[i, r + offsets[0] : r + offsets[-1] + 1, c + offsets[0] : c + offsets[-1] + 1] += terms[i, j]
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "physical": self.physical,
            "label": LABEL,
            "rank": len(self.basis),
            "patch_px": int(self.basis.shape[-1]),
            "fit_positions": int(len(self.positions_mm)),
            "singular_share": [round(float(s), 4) for s in self.singular_share],
            "kernel_scale_mm": [None if not np.isfinite(s) else round(float(s), 4) for s in self.scale_mm],
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
ARRAYS = ("basis", "positions_mm", "coefficients", "fitted", "scale_mm", "singular_share")


def _kernel(a: np.ndarray, b: np.ndarray, scale_mm: np.ndarray) -> np.ndarray:
    """Gaussian kernel (len(a), len(b)) with per-axis length scales (inf: axis ignored)."""
    d = (a[:, None, :] - b[None, :, :]) / scale_mm
    return np.exp(-0.5 * np.sum(d**2, axis=-1))


def _scale_mm(positions_mm: np.ndarray) -> np.ndarray:
    """Kernel length scales: :data:`KERNEL_STEPS` × the median step between distinct values of
    each axis (inf for an axis with one value)."""
    out = np.full(3, np.inf)
    for axis in range(3):
        values = np.unique(np.round(positions_mm[:, axis], 6))
        if len(values) > 1:
            out[axis] = KERNEL_STEPS * float(np.median(np.diff(values)))
    return out


def _patches(analysis: ResidualAnalysis, half: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residual patches (N, J, w, w), model focus energies (N, J) and which foci can be used."""
    model_signal = analysis.model_counts - analysis.registration.dark_level
    centres = analysis.model.centroid_px
    residual, inside = focus_patches(analysis.residual_counts, centres, half)
    model, _ = focus_patches(model_signal, centres, half)
    energy = model.sum(axis=(-2, -1))
    brightest = np.max(np.where(inside, energy, 0.0), axis=1, keepdims=True)
    usable = analysis.used[:, None] & inside & (energy > BRIGHT_SHARE * brightest)
    return residual, energy, usable


def _fit(
    residual: np.ndarray, energy: np.ndarray, usable: np.ndarray, positions_mm: np.ndarray, rank: int
) -> LowRankCorrection:
    """The correction fitted on the foci ``usable`` (N, J) of patches ``residual`` (N, J, w, w)."""
    width = residual.shape[-1]
    relative = residual[usable].reshape(-1, width * width) / energy[usable][:, None]
    weight = np.sqrt(energy[usable])[:, None]
    _, singular, vt = np.linalg.svd(relative * weight, full_matrices=False)
    rank = min(rank, len(singular))
    basis = vt[:rank]
    coefficients = np.zeros(usable.shape + (rank,))
    coefficients[usable] = relative @ basis.T
    images = usable.any(axis=1)
    return LowRankCorrection(
        basis=basis.reshape(rank, width, width),
        positions_mm=np.asarray(positions_mm, float)[images],
        coefficients=coefficients[images],
        fitted=usable[images],
        scale_mm=_scale_mm(np.asarray(positions_mm, float)),
        singular_share=singular[:rank] ** 2 / max(float(np.sum(singular**2)), 1e-30),
    )


def fit_correction(analysis: ResidualAnalysis, rank: int = 2, half: int = PATCH_HALF_PX) -> LowRankCorrection:
    """The correction fitted to every used image of ``analysis`` (the residual after the
    physical effects)."""
    residual, energy, usable = _patches(analysis, half)
    if not usable.any():
        raise ValueError("no focus bright enough to fit a correction to")
    return _fit(residual, energy, usable, analysis.positions_mm, rank)


def held_out_error(analysis: ResidualAnalysis, rank: int = 2, half: int = PATCH_HALF_PX) -> dict[str, Any]:
    """NMSE and χ² of the used images before and after the correction fitted *without* each
    (leave-one-position-out), summed over those images, with the NMSE a perfect model would
    leave (``nmse_noise_floor``: the noise model's variance over the signal's energy)."""
    residual, energy, usable = _patches(analysis, half)
    model_signal = analysis.model_counts - analysis.registration.dark_level
    signal = analysis.residual_counts + model_signal
    variance = analysis.noise.variance(model_signal)
    images = np.flatnonzero(usable.any(axis=1))
    before = after = norm = floor = 0.0
    chi2_before, chi2_after = [], []
    for i in images:
        keep = usable.copy()
        keep[i] = False
        if not keep.any():
            continue
        correction = _fit(residual, energy, keep, analysis.positions_mm, rank)
        added = correction.images(
            model_signal[i : i + 1], analysis.model.centroid_px[i : i + 1], analysis.positions_mm[i : i + 1]
        )[0]
        r0 = analysis.residual_counts[i].astype(np.float64)
        r1 = r0 - added
        before += float(np.sum(r0**2))
        after += float(np.sum(r1**2))
        norm += float(np.sum(signal[i].astype(np.float64) ** 2))
        floor += float(np.sum(variance[i]))
        chi2_before.append(float(np.mean(r0**2 / variance[i])))
        chi2_after.append(float(np.mean(r1**2 / variance[i])))
    return {
        "method": "leave-one-position-out: each image corrected by the correction fitted on the others",
        "images": int(len(chi2_before)),
        "nmse_before": round(before / max(norm, 1e-30), 6),
        "nmse_after": round(after / max(norm, 1e-30), 6),
        "nmse_noise_floor": round(floor / max(norm, 1e-30), 6),
        "chi2_before": round(float(np.mean(chi2_before)), 4) if chi2_before else None,
        "chi2_after": round(float(np.mean(chi2_after)), 4) if chi2_after else None,
    }
