"""Fixed-pattern offsets of the sensor's readout: every pixel of a column (or a row) offset by the
same few counts in every frame, a property of the readout's column amplifiers, not of the light.

After the fit, the residual where the model is dark (below :data:`DARK_SHARE` of each frame's
brightest model pixel above its median, as :mod:`.background` reads it), less each frame's median
there, is averaged down every column (and along every row) over all the frames used; what a
smooth background explains is taken out by subtracting a running median of :data:`SMOOTH` columns
(rows). Under white noise each mean scatters by σ/√n (σ the dark pixels' RMS within 6 robust σ,
n the pixels averaged); the pattern is named when its χ² exceeds its degrees of freedom by
:data:`SIGNIFICANCE` standard deviations, its RMS is at least :data:`MIN_RMS_SIGMA` × σ (below,
it adds nothing the noise model does not hold), and the two halves of the scan's frames agree on
it (correlation ≥ :data:`SAME_IN_EVERY_FRAME`: fixed, not a frame's own).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.ndimage import median_filter

__all__ = ["describe_fixed_pattern", "fixed_pattern"]

DARK_SHARE = 1e-3
SMOOTH = 15
SIGNIFICANCE = 4.0
MIN_RMS_SIGMA = 0.1
SAME_IN_EVERY_FRAME = 0.5


def _pattern(residual: np.ndarray, dark: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Means (L,) of ``residual`` (N, y, x) over the dark pixels, along ``axis`` of the frame (0:
    down each column, 1: along each row) and over the frames, less their running median; and
    the pixels averaged (L,)."""
    sums = np.where(dark, residual, 0.0).sum(axis=(0, 1 + axis))
    counts = dark.sum(axis=(0, 1 + axis)).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = sums / counts
    known = counts > 0
    out = np.full(len(means), np.nan)
    out[known] = means[known] - median_filter(means[known], size=SMOOTH, mode="nearest")
    return out, counts


def fixed_pattern(analysis) -> dict[str, Any] | None:
    """The column and row offsets the dark pixels share in every frame (module docstring):
    ``{columns_rms_counts, rows_rms_counts, columns_chi2_per_dof, rows_chi2_per_dof, worst_columns,
    worst_rows}`` for the axes named (the other's RMS None), or None."""
    used = np.flatnonzero(analysis.used)
    if len(used) < 2:
        return None
    model = analysis.model_counts[used].astype(np.float64)
    residual = analysis.residual_counts[used].astype(np.float64)
    median = np.median(model.reshape(len(used), -1), axis=1)[:, None, None]
    peak = model.reshape(len(used), -1).max(axis=1)[:, None, None]
    dark = (model - median) < DARK_SHARE * (peak - median)
    dark &= np.isfinite(residual)
    if dark.sum() < 100:
        return None
    levels = np.array([np.median(residual[i][dark[i]]) if dark[i].any() else 0.0 for i in range(len(used))])
    residual = residual - levels[:, None, None]
    values = residual[dark]
    # the RMS within 6 robust σ: the median of integer counts is coarse (1.4826 × an integer), the RMS is not
    robust = max(1.4826 * float(np.median(np.abs(values))), 1.0)
    sigma = float(np.sqrt(np.mean(values[np.abs(values) < 6.0 * robust] ** 2)))
    if sigma <= 0:
        return None
    halves = (slice(0, len(used), 2), slice(1, len(used), 2))
    found: dict[str, Any] = {}
    for axis, name in ((0, "columns"), (1, "rows")):
        pattern, counts = _pattern(residual, dark, axis)
        known = np.isfinite(pattern) & (counts > 0)
        if known.sum() < 2 * SMOOTH:
            continue
        chi2 = float(np.sum(pattern[known] ** 2 * counts[known])) / sigma**2
        dof = int(known.sum())
        rms = float(np.sqrt(np.mean(pattern[known] ** 2)))
        a, _ = _pattern(residual[halves[0]], dark[halves[0]], axis)
        b, _ = _pattern(residual[halves[1]], dark[halves[1]], axis)
        both = known & np.isfinite(a) & np.isfinite(b)
        agreement = float(np.corrcoef(a[both], b[both])[0, 1]) if both.sum() > 2 else 0.0
        if (
            chi2 - dof >= SIGNIFICANCE * np.sqrt(2.0 * dof)
            and rms >= MIN_RMS_SIGMA * sigma
            and agreement >= SAME_IN_EVERY_FRAME
        ):
            worst = np.argsort(-np.abs(np.where(known, pattern, 0.0)))[:5]
            found[name] = {
                "rms_counts": round(rms, 2),
                "chi2_per_dof": round(chi2 / dof, 1),
                "agreement": round(agreement, 2),
                "worst": [[int(k), round(float(pattern[k]), 1)] for k in worst],
            }
    if not found:
        return None
    return {**found, "noise_counts": round(sigma, 2)}


def describe_fixed_pattern(found: dict[str, Any]) -> str:
    """The warning for the pattern ``found`` by :func:`fixed_pattern`."""
    parts = [
        f"{name} offset by {p['rms_counts']:.2f} counts RMS (worst {', '.join(f'{k}: {v:+.1f}' for k, v in p['worst'][:3])}; "
        f"the two halves of the scan agree at {p['agreement']:.2f})"
        for name, p in found.items()
        if name in ("columns", "rows")
    ]
    return (
        f"the dark pixels hold a fixed pattern, the same in every frame: {' and '.join(parts)}, against a pixel noise "
        f"of {found['noise_counts']:.2f} counts: fixed-pattern offsets of the sensor's readout, not an effect of the "
        f"optics; the foci's energies over those columns or rows carry them: subtract a dark frame (or the "
        f"column/row offsets) before calibrating"
    )
