"""Problems of the acquisition, not of the optics: a source or exposure that drifts over the scan,
a stage that did not reach the positions the scan records.

The registration fits one flux scale for the whole scan. A calibration source whose power drifts
while the scan is taken (or exposures that are not what the frames record) makes each frame's
flux depart from it in the order the frames were taken, which no optical effect does: optical
effects change a focus's energy with the source's position, not with the time it was seen. After
the fit, each frame's flux is the median data/model energy ratio of its bright foci; when those
follow the acquisition order (the scan's file order) closely and change by more than
:data:`DRIFT_CHANGE` over the scan, the report says so.

Likewise every focus of a frame moves together when the source was not where ``positions.csv``
says (stage backlash, a position error): after the fit, a frame whose bright foci are displaced
together from the model by more than :data:`STAGE_SHIFT_PX` beyond the scan's common offset
(the median over the frames: the sensor's placement, which the registration fits) is named.
Optical effects move foci lenslet by lenslet or smoothly with the position; they are fitted
before this is judged.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import spearmanr

from cm2optics.calibrate.residual import ResidualAnalysis

__all__ = ["bright_foci", "flux_drift", "frame_flux", "frame_shifts", "stage_errors"]

#: Foci at least this share of their image's brightest (model) focus give the frame's flux and
#: shift, and the scan's magnification check: dimmer data centroids at the field's edge are mostly noise.
BRIGHT_FOCUS = 0.1
#: A trend along the acquisition order whose rank correlation is at least this…
DRIFT_RANK = 0.8
#: …and that changes the flux by at least this share from the first frame to the last is a drift.
DRIFT_CHANGE = 0.05
#: Fewer frames than this give no verdict.
MIN_FRAMES = 6
#: A frame whose bright foci are displaced together by more than this, px, beyond the scan's
#: common offset was not taken where its position says…
STAGE_SHIFT_PX = 0.3
#: …when at least this many frames are.
MIN_SHIFTED = 2


def bright_foci(analysis: ResidualAnalysis) -> np.ndarray:
    """(N, J) the foci of used frames at least :data:`BRIGHT_FOCUS` of their frame's brightest (model)."""
    energy = analysis.model.energy
    with np.errstate(invalid="ignore"):
        return (energy >= BRIGHT_FOCUS * np.nanmax(energy, axis=1, keepdims=True)) & analysis.used[:, None]


def frame_flux(analysis: ResidualAnalysis) -> np.ndarray:
    """(N,) each frame's flux relative to the model's: the median data/model energy ratio of its
    bright foci (NaN for frames left out or without a bright focus)."""
    ratio = np.where(bright_foci(analysis), analysis.energy_ratio, np.nan)
    out = np.full(len(ratio), np.nan)
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


def frame_shifts(analysis: ResidualAnalysis) -> np.ndarray:
    """(N, 2) each frame's common displacement of its foci from the model's (row, col) px: the
    median centroid error of its bright foci (NaN for frames left out or without one)."""
    error = np.where(bright_foci(analysis)[..., None], analysis.centroid_error_px, np.nan)
    out = np.full((len(error), 2), np.nan)
    has = np.isfinite(error).all(axis=-1).any(axis=1)
    out[has] = np.nanmedian(error[has], axis=1)
    return out


def stage_errors(analysis: ResidualAnalysis, pixel_um: float) -> str | None:
    """A warning when frames are displaced as a whole (module docstring), ``pixel_um`` the binned
    pixel pitch (µm); None when fewer than :data:`MIN_SHIFTED` frames depart from the scan's
    common offset by more than half :data:`STAGE_SHIFT_PX` or none by more than it."""
    shifts = frame_shifts(analysis)
    known = np.flatnonzero(np.isfinite(shifts).all(axis=1))
    if len(known) < MIN_FRAMES:
        return None
    beyond = np.linalg.norm(shifts[known] - np.median(shifts[known], axis=0), axis=1)
    if beyond.max() <= STAGE_SHIFT_PX or np.sum(beyond > STAGE_SHIFT_PX / 2) < MIN_SHIFTED:
        return None
    apart = float(np.max(np.linalg.norm(shifts[known, None] - shifts[None, known], axis=-1)))
    worst = known[np.argsort(beyond)[::-1][: min(6, np.sum(beyond > STAGE_SHIFT_PX / 2))]]
    return (
        f"the foci of whole frames are displaced together from the model, differently from frame to frame: up to "
        f"{apart:.2f} px ({apart * pixel_um:.0f} µm on the sensor) apart, {int(np.sum(beyond > STAGE_SHIFT_PX / 2))} "
        f"of {len(known)} frames more than {STAGE_SHIFT_PX / 2:.2g} px from the scan's common offset (most: "
        f"{', '.join(analysis.files[i] for i in worst)}): the source was not where positions.csv says (stage "
        f"backlash or a position error), which no effect of the optics does"
    )
