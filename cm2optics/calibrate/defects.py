"""Defective sensor pixels (hot, dead or stuck: single pixels, clusters, columns) found in a scan's own frames.

The foci move across the sensor during a scan, so most pixels are dark in most of its frames. A
pixel's departure from the median of its 5 × 5 neighbours is taken frame by frame (a background
that changes from frame to frame, light that scales with the exposure, cancels there), then its
median over the frames: where the model's median light is negligible and that median exceeds
:data:`DEFECT_SIGMA` robust standard deviations (of the departures over the sensor, or locally
where a background makes them larger), the pixel is a defect of the sensor, not of the optics (a
hot pixel, a dead column reading 0, a saturated cluster). Defects take no part in any fit (registration, noise, χ²) and
are filled, frame by frame, with the mean of their good neighbours for the focus measurements;
without this a hot pixel saturated in every frame left every frame out as "saturated".
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, median_filter

from cm2optics.calibrate.noise import robust_sigma

__all__ = ["defective_pixels", "describe_defects", "fill_defects"]

#: A pixel's median over the frames departing from its neighbours' by more than this many robust
#: standard deviations (of that departure over the sensor's dark pixels) is a defect.
DEFECT_SIGMA = 10.0
#: The departure's σ is taken no smaller than this, counts (noise-free frames: one count step).
MIN_SIGMA_COUNTS = 1.0
#: Pixels where the model's median light over the frames exceeds this share of its peak are not
#: judged (a source kept near one place in most frames lights the same pixels in most of them).
MODEL_LIT = 1e-3
#: Neighbourhood of the median a pixel is compared with, px.
NEIGHBOURHOOD_PX = 5
#: Neighbourhood whose median absolute departure gives the local noise, px.
NOISE_NEIGHBOURHOOD_PX = 15
#: σ of the Gaussian weights of the good neighbours that fill a defect, px.
FILL_SIGMA_PX = 1.5
#: Frames filled at a time.
FILL_BLOCK = 16


def defective_pixels(counts: np.ndarray, model_rate: np.ndarray, exposure_ms: np.ndarray) -> np.ndarray:
    """(y, x) bool: the defects of the sensor (module docstring) in frames ``counts`` (N, y, x)
    raw counts, against the model's images ``model_rate`` (N, y, x) per ms of the same positions
    (any flux scale: only where it is dark matters) taken with ``exposure_ms`` (N,)."""
    frames = np.asarray(counts, np.float32)
    local = median_filter(frames, size=(1, NEIGHBOURHOOD_PX, NEIGHBOURHOOD_PX), mode="nearest")
    departure = np.median(frames - local, axis=0)  # each frame against its own neighbourhood first
    expected = np.asarray(model_rate, np.float32) * np.asarray(exposure_ms, np.float32)[:, None, None]
    model = np.median(expected, axis=0)
    dark = model <= MODEL_LIT * max(float(np.max(expected)), 1e-30)
    if not dark.any():
        return np.zeros(departure.shape, bool)
    sigma = max(robust_sigma(departure[dark]), MIN_SIGMA_COUNTS)
    # where a background raises the level (room light on long exposures) its shot noise does too:
    # the departure is judged against its local spread as well (a defect is too rare to set it)
    local = 1.4826 * median_filter(np.abs(departure), size=NOISE_NEIGHBOURHOOD_PX, mode="nearest")
    return dark & (np.abs(departure) > DEFECT_SIGMA * np.maximum(local, sigma))


def fill_defects(counts: np.ndarray, defects: np.ndarray) -> np.ndarray:
    """Frames ``counts`` (N, y, x) with the ``defects`` (y, x) replaced by the Gaussian-weighted
    mean of their good neighbours, rounded to counts (float32; frames' other pixels unchanged)."""
    good = (~defects).astype(np.float32)
    sigma = (0.0, FILL_SIGMA_PX, FILL_SIGMA_PX)
    weight = gaussian_filter(good[None], sigma)[0]
    out = np.asarray(counts, np.float32).copy()
    rows, cols = np.nonzero(defects)
    if rows.size == 0:
        return out
    reached = weight[rows, cols] > 1e-3  # else no good neighbour: the frame's median (its dark)
    for start in range(0, len(out), FILL_BLOCK):  # a few frames at a time: the memory of a block
        block = out[start : start + FILL_BLOCK]
        mean = gaussian_filter(block * good[None], sigma)[:, rows, cols] / np.maximum(weight[rows, cols], 1e-6)
        fallback = np.median(block[:, ~defects], axis=1)[:, None]
        block[:, rows, cols] = np.rint(np.where(reached[None], mean, fallback))
    return out


def describe_defects(defects: np.ndarray) -> dict[str, object]:
    """The defects as the report lists them: how many pixels, the whole columns and rows among
    them (more than half their pixels defective) and up to five other pixels (row, col)."""
    columns = np.flatnonzero(defects.mean(axis=0) > 0.5)
    rows = np.flatnonzero(defects.mean(axis=1) > 0.5)
    rest = defects.copy()
    rest[:, columns] = False
    rest[rows, :] = False
    return {
        "pixels": int(defects.sum()),
        "columns": [int(c) for c in columns],
        "rows": [int(r) for r in rows],
        "other_pixels": [[int(r), int(c)] for r, c in np.argwhere(rest)[:5]],
    }
