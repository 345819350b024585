"""Problems of the acquisition, not of the optics: a source or exposure that drifts over the scan.

The registration fits one flux scale for the whole scan. A calibration source whose power drifts
while the scan is taken (or exposures that are not what the frames record) makes each frame's
flux depart from it in the order the frames were taken, which no optical effect does: optical
effects change a focus's energy with the source's position, not with the time it was seen. After
the fit, each frame's flux is the median data/model energy ratio of its bright foci; when those
follow the acquisition order (the scan's file order) closely and change by more than
:data:`DRIFT_CHANGE` over the scan, the report says so.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import spearmanr

from cm2optics.calibrate.residual import ResidualAnalysis

__all__ = ["flux_drift", "frame_flux"]

#: Foci at least this share of their image's brightest (model) focus give the frame's flux.
BRIGHT_FOCUS = 0.1
#: A trend along the acquisition order whose rank correlation is at least this…
DRIFT_RANK = 0.8
#: …and that changes the flux by at least this share from the first frame to the last is a drift.
DRIFT_CHANGE = 0.05
#: Fewer frames than this give no verdict.
MIN_FRAMES = 6


def frame_flux(analysis: ResidualAnalysis) -> np.ndarray:
    """(N,) each frame's flux relative to the model's: the median data/model energy ratio of its
    bright foci (NaN for frames left out or without a bright focus)."""
    energy = analysis.model.energy
    with np.errstate(invalid="ignore"):
        bright = energy >= BRIGHT_FOCUS * np.nanmax(energy, axis=1, keepdims=True)
        ratio = np.where(bright & analysis.used[:, None], analysis.energy_ratio, np.nan)
    out = np.full(len(energy), np.nan)
    has = np.isfinite(ratio).any(axis=1)
    out[has] = np.nanmedian(ratio[has], axis=1)
    return out


def flux_drift(analysis: ResidualAnalysis) -> str | None:
    """A warning when the frames' flux after the fit follows the acquisition order (module
    docstring); None otherwise."""
    flux = frame_flux(analysis)
    order = np.flatnonzero(np.isfinite(flux))
    if len(order) < MIN_FRAMES:
        return None
    rank = float(spearmanr(order, flux[order]).statistic)
    slope, intercept = np.polyfit(order, flux[order], 1)
    first, last = intercept + slope * order[0], intercept + slope * order[-1]
    change = (last - first) / max(abs(first), 1e-12)
    if not (abs(rank) >= DRIFT_RANK and abs(change) >= DRIFT_CHANGE):
        return None
    return (
        f"the frames' flux changes by {change:+.0%} from the first frame to the last, following the order in "
        f"which they were taken (rank correlation {rank:+.2f}): the calibration source or the exposures drifted "
        f"during the scan, which no effect of the optics does; effects that change the foci's energy "
        f"(source_profile, vignetting, lenslet_transmission) may hold part of it: re-take the scan or "
        f"normalise each frame by a reference measurement of the source"
    )
