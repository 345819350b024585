"""Background light the model lacks that varies over the sensor: room light through a gap, a
leak that falls on one side, a glow of the sensor's electronics.

The registration fits one dark level and the attribution a uniform leakage; what is left away
from the foci (where the model puts less than :data:`DARK_SHARE` of its brightest pixel above
its median: most pixels are dark, and a fitted leakage lifts them all) is fitted
frame by frame by a quadratic surface in the sensor's rows and columns (least squares on every
:data:`SAMPLE`-th pixel). The structure is named when, over the scan, the surfaces beat a constant
by :data:`BIC_MARGIN` on the Bayesian information criterion (noise level profiled out) and
their range at the median exposure is at least :data:`MIN_RANGE_SIGMA` times the dark pixels'
scatter about them (the noise model's read noise is estimated on those same pixels, and an
unmodelled background inflates it), so that the foci's residuals can be read above it
(:mod:`.unexplained`); whether it follows the exposures tells light (it does) from a pattern of
the sensor (it does not).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import spearmanr

from cm2optics.calibrate.residual import ResidualAnalysis

__all__ = ["BackgroundStructure", "background_entry", "background_structure", "quadratic_terms"]

#: Pixels where the model puts less than this share of its brightest pixel are "away from the foci".
DARK_SHARE = 1e-3
#: Every this-many-th pixel (in rows and columns) of the dark region enters the fit.
SAMPLE = 2
#: The surfaces must beat a constant background by this much BIC over the scan…
BIC_MARGIN = 10.0
#: …and span at least this many times the dark pixels' noise σ at the median exposure.
MIN_RANGE_SIGMA = 1.0
#: A rank correlation of the surfaces' ranges with the exposures of at least this is light.
FOLLOWS_EXPOSURE = 0.6


@dataclass(frozen=True)
class BackgroundStructure:
    """The fitted surfaces of the residual away from the foci, their level included (a dark level
    or leakage that the registration got wrong with the structure there): quadratic coefficients
    (N, 6) in counts on pixel coordinates scaled to
    [−1, 1] over ``shape`` (zero for frames left out or too bright to fit); their range at the median exposure
    (counts), where they are highest and lowest (row, col) px, and the rank correlation of the
    frames' ranges with their exposures."""

    coefficients: np.ndarray
    shape: tuple[int, int]
    range_counts: float
    highest_px: tuple[int, int]
    lowest_px: tuple[int, int]
    exposure_rank: float

    def surface(self, frame: int) -> np.ndarray:
        """(y, x) counts: frame ``frame``'s surface."""
        rows, cols = np.mgrid[0 : self.shape[0], 0 : self.shape[1]]
        return (_terms(rows.ravel(), cols.ravel(), self.shape) @ self.coefficients[frame]).reshape(self.shape)

    def patches(self, centres: np.ndarray, half: int) -> np.ndarray:
        """(N, J, 2·half + 1, 2·half + 1) counts: the surfaces on the square patches centred on the
        pixel nearest each of ``centres`` (N, J, 2) (as :func:`~.features.focus_patches` cuts
        them; zeros for a NaN centre)."""
        known = np.isfinite(centres).all(axis=-1)
        centre = np.rint(np.where(known[..., None], centres, 0.0))
        offsets = np.arange(-half, half + 1, dtype=float)
        rows = np.broadcast_to(
            centre[..., 0, None, None] + offsets[:, None], (*centre.shape[:2], len(offsets), len(offsets))
        )
        cols = np.broadcast_to(centre[..., 1, None, None] + offsets[None, :], rows.shape)
        terms = _terms(rows.ravel(), cols.ravel(), self.shape).reshape(*rows.shape, 6)
        values = np.einsum("njpqk,nk->njpq", terms, self.coefficients)
        return np.where(known[..., None, None], values, 0.0)


def quadratic_terms(r: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(P, 6) the terms 1, r, c, r², r·c, c² of scaled coordinates ``r``, ``c`` (P,)."""
    return np.column_stack([np.ones(len(r)), r, c, r * r, r * c, c * c])


def _terms(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(P, 6) the quadratic terms of pixel coordinates scaled to [−1, 1]."""
    return quadratic_terms(2.0 * rows / max(shape[0] - 1, 1) - 1.0, 2.0 * cols / max(shape[1] - 1, 1) - 1.0)


def background_structure(analysis: ResidualAnalysis, exposure_ms: np.ndarray) -> BackgroundStructure | None:
    """The background structure of the residual after the fit (module docstring), or None."""
    model_signal = analysis.model_counts - analysis.registration.dark_level
    shape = model_signal.shape[-2:]
    grid_rows, grid_cols = np.mgrid[0 : shape[0] : SAMPLE, 0 : shape[1] : SAMPLE]
    full = _terms(*np.mgrid[0 : shape[0], 0 : shape[1]].reshape(2, -1), shape)  # (y·x, 6)
    coefficients = np.zeros((len(model_signal), 6))
    bic_constant = bic_surface = 0.0
    fitted = np.zeros(len(model_signal), bool)
    scatter = np.zeros(len(model_signal))  # the dark pixels' noise about each surface, counts
    for i in np.flatnonzero(analysis.used):
        floor = float(np.median(model_signal[i]))  # most pixels are dark; a fitted leakage lifts them all
        dark = model_signal[i, ::SAMPLE, ::SAMPLE] - floor <= DARK_SHARE * (float(model_signal[i].max()) - floor)
        values = analysis.residual_counts[i, ::SAMPLE, ::SAMPLE][dark].astype(np.float64)
        if len(values) < 100:
            continue
        design = _terms(grid_rows[dark], grid_cols[dark], shape)
        solution, *_ = np.linalg.lstsq(design, values, rcond=None)
        n = len(values)
        rss_surface = max(float(np.sum((values - design @ solution) ** 2)), 1e-300)
        rss_constant = max(float(np.sum((values - values.mean()) ** 2)), 1e-300)
        bic_surface += n * np.log(rss_surface / n) + 6 * np.log(n)
        bic_constant += n * np.log(rss_constant / n) + np.log(n)
        coefficients[i] = solution
        scatter[i] = np.sqrt(rss_surface / n)
        fitted[i] = True
    frames = np.flatnonzero(fitted)
    if not frames.size or bic_surface > bic_constant - BIC_MARGIN:
        return None
    exposure = np.asarray(exposure_ms, float)
    ranges = np.array([np.ptp(full @ coefficients[i]) for i in frames])  # frame by frame: (y·x) each
    rank = float(spearmanr(exposure[frames], ranges).statistic) if np.ptp(exposure[frames]) > 0 else float("nan")
    median = float(np.median(exposure[frames]))
    follows = np.isfinite(rank) and rank >= FOLLOWS_EXPOSURE
    scaled = coefficients[frames] * (median / exposure[frames])[:, None] if follows else coefficients[frames]
    typical = (full @ np.median(scaled, axis=0)).reshape(shape)
    span = float(np.ptp(typical))
    if span < MIN_RANGE_SIGMA * float(np.median(scatter[frames])):
        return None
    high = np.unravel_index(int(np.argmax(typical)), shape)
    low = np.unravel_index(int(np.argmin(typical)), shape)
    return BackgroundStructure(
        coefficients,
        (int(shape[0]), int(shape[1])),
        span,
        (int(high[0]), int(high[1])),
        (int(low[0]), int(low[1])),
        rank if np.isfinite(rank) else 0.0,
    )


def background_entry(found: BackgroundStructure, analysis: ResidualAnalysis, lenslets: int) -> dict[str, object]:
    """The ``unexplained`` entry of a background structure: every lenslet, the whole field and
    every depth, the share of the model's signal it holds, and what it looks like."""
    used = analysis.used
    signal = np.abs(analysis.model_counts[used] - analysis.registration.dark_level).sum()
    surfaces = (found.surface(i) for i in np.flatnonzero(used))
    background = sum(float(np.abs(surface - surface.mean()).sum()) for surface in surfaces)  # the structure
    fraction = background / max(float(signal), 1e-30)
    field = np.hypot(analysis.positions_mm[used, 0], analysis.positions_mm[used, 1])
    source = (
        "it grows with the exposure (rank correlation "
        f"{found.exposure_rank:+.2f}): light reaching the sensor that the model lacks (room light, a leak through "
        "the housing, a filter's leakage that is not uniform)"
        if found.exposure_rank >= FOLLOWS_EXPOSURE
        else f"it does not follow the exposure (rank correlation {found.exposure_rank:+.2f}): a pattern of the "
        "sensor or its electronics (bias structure, amplifier glow)"
    )
    return {
        "lenslets": list(range(lenslets)),
        "field_mm": [round(float(field.min()), 3), round(float(field.max()), 3)],
        "depths_mm": sorted({round(float(z), 4) for z in analysis.positions_mm[used, 2]}),
        "energy_fraction": round(fraction, 5),
        "description": (
            f"background structure, not of the foci: away from them the residual varies smoothly over the sensor by "
            f"{found.range_counts:.1f} counts at the median exposure, highest near (row, col) {list(found.highest_px)} "
            f"px and lowest near {list(found.lowest_px)} px; {source}; the foci's residuals are read above it"
        ),
    }
