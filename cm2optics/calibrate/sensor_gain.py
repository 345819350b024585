"""A sensor whose gain varies smoothly over its area (an uncorrected flat field): one pattern that
every focus sees where it lands, whatever its lenslet and the source's position.

The optical effects that change a focus's energy with the field (the source's angular profile,
vignetting, a lenslet's transmission) depend on where the source sits relative to the focus's own
lenslet: on the focus's offset from the point below its lenslet's vertex (the focus of a source
straight in front of it), or on the lenslet. A sensor gain depends on the focus's absolute
position on the sensor. After the fit, the bright foci's energy ratios data/model (relative to
their common, or each frame's own, flux) are fitted by a quadratic in each of those, and by one
constant per lenslet; a gain pattern is named when the quadratic in sensor position wins by
:data:`BIC_MARGIN` on the Bayesian information criterion (noise level profiled out) over all the
others and over a constant, and when it spans at least :data:`GAIN_MIN`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cm2optics.calibrate.acquisition import bright_foci, frame_flux
from cm2optics.calibrate.background import quadratic_terms
from cm2optics.calibrate.residual import ResidualAnalysis

__all__ = ["BIC_MARGIN", "GAIN_MIN", "describe_sensor_gain", "sensor_gain"]

#: The quadratic in sensor position must beat every other description by this much BIC.
BIC_MARGIN = 10.0
#: …and its values over the foci must span at least this share.
GAIN_MIN = 0.03
#: Energy ratios outside this range are no gain (a clipped or lost focus): left out.
RATIO_RANGE = (0.2, 5.0)
#: Fewer bright foci than this give no verdict.
MIN_FOCI = 20


def _quadratic(points: np.ndarray) -> np.ndarray:
    """(F, 6) the quadratic terms of points (F, 2)."""
    return quadratic_terms(points[:, 0], points[:, 1])


def _bic(design: np.ndarray, values: np.ndarray) -> tuple[float, np.ndarray]:
    """BIC n·ln(RSS/n) + k·ln n of the least-squares fit of ``values`` by ``design``, and the fit."""
    solution, *_ = np.linalg.lstsq(design, values, rcond=None)
    fitted = design @ solution
    rss = max(float(np.sum((values - fitted) ** 2)), 1e-300)
    n, k = len(values), np.linalg.matrix_rank(design)
    return n * np.log(rss / n) + k * np.log(n), fitted


def sensor_gain(analysis: ResidualAnalysis, vertices_px: np.ndarray, per_frame: bool = False) -> dict[str, Any] | None:
    """The sensor gain pattern the foci's energies follow (module docstring), or None.

    vertices_px: (J, 2) (row, col) px below each lenslet's vertex.
    per_frame: each frame's flux is its own (a source that drifted, :mod:`.acquisition`).
    Returns ``{range, lowest_px, highest_px, foci, bic_gain}``: the relative gain's lowest and
    highest value over the foci (normalised to their median), where they are, the foci used, and
    the BIC margin over the next best description.
    """
    ratio = analysis.energy_ratio
    flux = frame_flux(analysis)[:, None] if per_frame else np.nanmedian(ratio[bright_foci(analysis)])
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = ratio / flux
    use = bright_foci(analysis) & np.isfinite(relative) & (relative > RATIO_RANGE[0]) & (relative < RATIO_RANGE[1])
    use &= np.isfinite(analysis.model.centroid_px).all(axis=-1) & np.isfinite(vertices_px).all(axis=-1)[None]
    if use.sum() < MIN_FOCI:
        return None
    frame, lenslet = np.nonzero(use)
    values = relative[use]
    centres = analysis.model.centroid_px[use]
    scale = max(float(np.ptp(centres, axis=0).max()) / 2, 1.0)
    middle = centres.mean(axis=0)
    on_sensor = _quadratic((centres - middle) / scale)
    candidates = {
        "constant": np.ones((len(values), 1)),
        "offset from the lenslet": _quadratic((centres - vertices_px[lenslet]) / scale),
        "per lenslet": (lenslet[:, None] == np.unique(lenslet)[None, :]).astype(float),
    }
    gain_bic, fitted = _bic(on_sensor, values)
    other = min(_bic(design, values)[0] for design in candidates.values())
    spread = float(fitted.max() - fitted.min()) / max(float(np.median(fitted)), 1e-12)
    if gain_bic > other - BIC_MARGIN or spread < GAIN_MIN:
        return None
    median = float(np.median(fitted))
    low, high = int(np.argmin(fitted)), int(np.argmax(fitted))
    return {
        "range": [round(float(fitted[low]) / median, 4), round(float(fitted[high]) / median, 4)],
        "lowest_px": [round(float(v), 1) for v in centres[low]],
        "highest_px": [round(float(v), 1) for v in centres[high]],
        "foci": int(len(values)),
        "bic_gain": round(float(other - gain_bic), 1),
    }


def describe_sensor_gain(found: dict[str, Any], binning: int) -> str:
    """The warning for a gain pattern ``found`` by :func:`sensor_gain` (``binning``: the scan's)."""
    low, high = found["range"]
    return (
        f"the foci's energies follow one smooth pattern over the sensor, whatever their lenslet and the source's "
        f"position: a relative gain from {low:.3f} (near row, col {found['lowest_px']} px at {binning}× binning) "
        f"to {high:.3f} (near {found['highest_px']} px) over {found['foci']} foci (ΔBIC {found['bic_gain']:.0f} "
        f"over any optical description): a sensor gain non-uniformity (an uncorrected flat field or a "
        f"sensor-side stain), not an effect of the optics: flat-field the frames (sensor_gain)"
    )
