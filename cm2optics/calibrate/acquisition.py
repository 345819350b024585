"""Problems of the acquisition, not of the optics: a source or exposure that drifts over the scan,
a stage that did not reach the positions the scan records.

The registration fits one flux scale for the whole scan. A calibration source whose power drifts
while the scan is taken (or exposures that are not what the frames record) makes each frame's
flux depart from it in the order the frames were taken, which no optical effect does: optical
effects change a focus's energy with the source's position, not with the time it was seen. After
the fit, each frame's flux is the median data/model energy ratio of its bright foci; when those
follow the acquisition order (the scan's file order) closely and change by more than
:data:`DRIFT_CHANGE` over the scan, the report says so.

Frames whose recorded exposure is wrong (or during which the source flickered) have every bright
focus brighter or dimmer by one common factor beyond what the foci of the frame scatter by
among themselves, at no trend along the order (:func:`frame_flux_errors`).

Likewise every focus of a frame moves together when the source was not where ``positions.csv``
says (stage backlash, a position error): after the fit, a frame whose bright foci are displaced
together from the model by more than :data:`STAGE_SHIFT_PX` beyond the scan's common offset
(the median over the frames: the sensor's placement, which the registration fits) is named.
Optical effects move foci lenslet by lenslet or smoothly with the position; they are fitted
before this is judged. Each frame's motion is fitted to its bright foci's centroid errors as a
translation plus a change of the foci's spread (:func:`frame_motion`), with standard errors from
the scatter of the foci about that fit pooled over the scan, or the frame's own when its foci
disagree more: the displacement of a frame whose foci are dim over a heavy background is noise,
and is named only when it is :data:`SIGNIFICANCE` standard errors beyond the common offset.
The change of spread is taken about the point the foci spread from when the source's depth
changes: the foci of lenslet vertices v_j land at (1 + m)·v_j − m·S (S below the source), so a
depth error moves each by δm·(v_j − S), about S — not about the foci's mean, which an off-axis
source's foci do not surround. A z error therefore displaces no frame.

A stage whose z steps are not the recorded ones (a z scale error) changes the foci's spread
instead: the spread of a lenslet array's foci is 1 + m(z) times the lenslets' (m the chief-ray
magnification at the source's depth), so a frame whose source sat δz off spreads its foci by
δz · d ln(1 + m)/dz. The δz of every frame, regressed on its recorded z, gives the scale error
(its slope) when the scan holds two depths or more (:func:`stage_z_scale`).

A stage whose x and y axes are rotated against the design's, or whose lateral steps are not the
recorded ones, puts each source off by an error that grows linearly with its recorded position:
each frame's translation, carried back to the source's plane through the model's own foci
(their motion per mm of source x and y at that depth, :func:`lateral_jacobians`), regressed on the
recorded x and y gives that linear map, whose antisymmetric part is the axes' rotation and whose
diagonal the lateral scales (:func:`stage_xy_map`); a backlash or a random position error has
no such trend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import spearmanr

from cm2optics.calibrate.residual import ResidualAnalysis
from cm2optics.design import SystemDesign
from cm2optics.optics import first_order

__all__ = [
    "FrameMotion",
    "bright_foci",
    "flux_drift",
    "frame_flux",
    "frame_flux_errors",
    "frame_motion",
    "spread_centres",
    "spread_rate_per_mm",
    "lateral_jacobians",
    "stage_errors",
    "stage_xy_map",
    "stage_z_scale",
]

#: Foci at least this share of their image's brightest (model) focus give the frame's flux and
#: shift, and the scan's magnification check: dimmer data centroids at the field's edge are mostly noise.
BRIGHT_FOCUS = 0.1
#: A trend along the acquisition order whose rank correlation is at least this…
DRIFT_RANK = 0.8
#: …and that changes the flux by at least this share from the first frame to the last is a drift.
DRIFT_CHANGE = 0.05
#: Fewer frames than this give no verdict.
MIN_FRAMES = 6
#: A frame whose flux departs from the scan's by less than this share is not named (exposures are
#: recorded to ≈ 1 %; an optical misfit left by the fit moves a frame's foci by a few % each).
FRAME_FLUX_MIN = 0.03
#: A frame whose bright foci are displaced together by more than this, px, beyond the scan's
#: common offset was not taken where its position says…
STAGE_SHIFT_PX = 0.3
#: …when at least this many frames are.
MIN_SHIFTED = 2
#: A frame's displacement, or a z scale, counts only this many standard errors beyond zero.
SIGNIFICANCE = 4.0
#: A frame's displacement is judged on at least this many foci that agree with each other (when
#: the scan's frames hold that many): one or two dim foci's centroids can be far off together.
MIN_AGREEING_FOCI = 3
#: A z scale error smaller than this share of the recorded steps is not named.
Z_SCALE_MIN = 0.03
#: A rotation of the stage's x, y axes smaller than this (degrees) is not named…
XY_ROTATION_MIN_DEG = 0.2
#: …nor a lateral scale error smaller than this share of the recorded steps.
XY_SCALE_MIN = 0.03


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


def frame_flux_errors(analysis: ResidualAnalysis) -> str | None:
    """A warning naming the frames whose flux (:func:`frame_flux`) departs from the scan's median
    by at least :data:`FRAME_FLUX_MIN` and :data:`SIGNIFICANCE` standard errors: the standard error
    of a frame's median ratio is 1.253·σ/√n over its n bright foci, σ the foci's scatter about
    their frame's median pooled over the scan (1.4826 × the median absolute departure); frames
    with fewer than :data:`MIN_AGREEING_FOCI` bright foci are not judged. None when no frame is
    named or fewer than :data:`MIN_FRAMES` are judged."""
    bright = bright_foci(analysis) & np.isfinite(analysis.energy_ratio)
    flux = frame_flux(analysis)
    counts = bright.sum(axis=1)
    judged = np.flatnonzero(np.isfinite(flux) & (counts >= MIN_AGREEING_FOCI))
    if len(judged) < MIN_FRAMES:
        return None
    departures = np.concatenate([analysis.energy_ratio[i][bright[i]] / flux[i] - 1.0 for i in judged])
    sigma = 1.4826 * float(np.median(np.abs(departures)))
    common = float(np.median(flux[judged]))
    change = flux[judged] / common - 1.0
    se = 1.253 * sigma / np.sqrt(counts[judged])
    named = (np.abs(change) >= FRAME_FLUX_MIN) & (np.abs(change) >= SIGNIFICANCE * se)
    if not named.any():
        return None
    order = np.argsort(-np.abs(np.where(named, change, 0.0)))[: int(named.sum())]
    listed = ", ".join(f"{analysis.files[judged[k]]} {change[k]:+.1%}" for k in order[:8])
    more = f" and {int(named.sum()) - 8} more" if named.sum() > 8 else ""
    return (
        f"{int(named.sum())} of {len(judged)} frames are brighter or dimmer as a whole than the scan's flux says, "
        f"every bright focus by one common factor ({listed}{more}; the foci of a frame scatter by "
        f"{sigma:.1%} among themselves): their recorded exposures are wrong or the source's power changed "
        f"between frames, which no effect of the optics does; the unexplained residual is read against each "
        f"frame's own flux"
    )


@dataclass(frozen=True)
class FrameMotion:
    """Each frame's bright foci against the model's: a common translation ``shift_px`` (N, 2)
    (row, col) px and a relative change of their spread ``expansion`` (N,) (0: as the model's;
    NaN with fewer than two bright foci), with standard errors (N,) (0 when the scan leaves no
    scatter to estimate them from), and the foci that agree on them (N,); NaN (0 foci) for frames
    left out or without a bright focus."""

    shift_px: np.ndarray
    shift_se_px: np.ndarray
    expansion: np.ndarray
    expansion_se: np.ndarray
    foci: np.ndarray


def frame_motion(analysis: ResidualAnalysis, vertices_px: np.ndarray | None = None) -> FrameMotion:
    """Fit each frame's centroid errors e_j = t + s·(m_j − m̄) over its bright foci (m_j the
    model's centroids, m̄ their mean) by least squares; the foci's scatter about the fit, pooled
    over the scan (median absolute residual), or the frame's own where larger, gives the
    standard errors. A focus whose misfit is beyond :data:`SIGNIFICANCE` times the pooled scatter
    (a centroid that a background or a neighbour pulled far off) is left out of its frame's fit,
    the worst first, down to two foci. With the lenslets' vertices ``vertices_px`` (J, 2) (row,
    col) px (:func:`cm2optics.calibrate.tracer.lenslet_vertices_px`; NaN for none) the
    translation is the one about the centre of spread (:func:`spread_centres`), not about m̄."""
    bright = bright_foci(analysis) & np.isfinite(analysis.centroid_error_px).all(axis=-1)
    frames = np.flatnonzero(bright.any(axis=1))
    errors = {i: analysis.centroid_error_px[i][bright[i]] for i in frames}
    spreads = {
        i: analysis.model.centroid_px[i][bright[i]] - analysis.model.centroid_px[i][bright[i]].mean(axis=0)
        for i in frames
    }
    fits = {i: _frame_fit(errors[i], spreads[i]) for i in frames}
    sigma = _pooled_scatter(fits.values())
    foci = np.zeros(len(bright), int)
    for i in frames:
        keep = np.ones(len(errors[i]), bool)
        while sigma > 0 and keep.sum() > 2 and fits[i][2] is not None:
            misfit = np.linalg.norm(fits[i][2].reshape(-1, 2), axis=1)
            if misfit.max() <= SIGNIFICANCE * sigma:
                break
            keep[np.flatnonzero(keep)[np.argmax(misfit)]] = False
            fits[i] = _frame_fit(errors[i][keep], spreads[i][keep])
        foci[i] = keep.sum()
    sigma = _pooled_scatter(fits.values())
    n = len(bright)
    centres = np.full((n, 2), np.nan) if vertices_px is None else spread_centres(analysis, vertices_px)
    shift, shift_se = np.full((n, 2), np.nan), np.full(n, np.nan)
    expansion, expansion_se = np.full(n, np.nan), np.full(n, np.nan)
    for i, (solution, variance, residual) in fits.items():
        scatter = (
            sigma
            if residual is None
            else max(sigma, float(np.sqrt(np.mean(residual**2) * len(residual) / (len(residual) - 3))))
        )
        shift[i], shift_se[i] = solution[:2], scatter * np.sqrt(variance[0])
        expansion[i], expansion_se[i] = solution[2], scatter * np.sqrt(variance[2])
        lever = analysis.model.centroid_px[i][bright[i]].mean(axis=0) - centres[i]
        if np.isfinite(lever).all() and np.isfinite(solution[2]):  # e = t' + s·(m_j − S) = t' + s·(m̄ − S) + s·(m_j − m̄)
            shift[i] = solution[:2] - solution[2] * lever
            shift_se[i] = scatter * np.sqrt(variance[0] + float(lever @ lever) * variance[2])
    return FrameMotion(shift, shift_se, expansion, expansion_se, foci)


def spread_centres(analysis: ResidualAnalysis, vertices_px: np.ndarray) -> np.ndarray:
    """(N, 2) the sensor point each frame's foci spread from as the source's depth changes (row,
    col) px: the model's centroids m_j fitted as a·v_j + b over the lenslets' vertices v_j
    (foci (1 + m)·v_j − m·S: a = 1 + m, b = −m·S), S = b / (1 − a); NaN where fewer than three
    foci are known or the foci do not spread (a ≈ 1)."""
    out = np.full((len(analysis.positions_mm), 2), np.nan)
    vertices = np.asarray(vertices_px, float)
    for i, centroids in enumerate(analysis.model.centroid_px):
        known = np.isfinite(centroids).all(axis=1) & np.isfinite(vertices).all(axis=1)
        if known.sum() < 3:
            continue
        v, m = vertices[known], centroids[known]
        dv = v - v.mean(axis=0)
        a = float(np.sum(dv * (m - m.mean(axis=0))) / max(np.sum(dv**2), 1e-12))
        if abs(1.0 - a) > 1e-3:
            out[i] = (m.mean(axis=0) - a * v.mean(axis=0)) / (1.0 - a)
    return out


def _frame_fit(error: np.ndarray, spread: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(t_row, t_col, s), their variances per unit noise variance, and the residuals (None: no
    degree of freedom left) of e = t + s·spread over one frame's foci (F, 2); with one focus,
    or foci on one point, the translation alone (s NaN)."""
    if len(error) < 2 or not np.any(spread):
        return np.array([*error.mean(axis=0), np.nan]), np.array([1.0, 1.0, np.nan]) / len(error), None
    design = np.zeros((2 * len(error), 3))
    design[0::2, 0], design[1::2, 1] = 1.0, 1.0
    design[:, 2] = spread.ravel()
    solution, *_ = np.linalg.lstsq(design, error.ravel(), rcond=None)
    residual = error.ravel() - design @ solution
    return solution, np.diag(np.linalg.pinv(design.T @ design)), (residual if len(residual) > 3 else None)


def _pooled_scatter(fits) -> float:
    """The centroids' noise (px) per coordinate: the median absolute residual of the frames' fits
    (1.4826 × for a normal scatter, corrected for the 3 fitted parameters); 0 without residuals."""
    residuals = [r for _, _, r in fits if r is not None]
    if not residuals:
        return 0.0
    scatter = np.concatenate(residuals)
    dof = sum(len(r) - 3 for r in residuals)
    return 1.4826 * float(np.median(np.abs(scatter))) * float(np.sqrt(len(scatter) / dof))


def stage_errors(analysis: ResidualAnalysis, pixel_um: float, vertices_px: np.ndarray | None = None) -> str | None:
    """A warning when frames are displaced as a whole (module docstring), ``pixel_um`` the binned
    pixel pitch (µm), ``vertices_px`` the lenslets' vertices (:func:`frame_motion`); None when fewer than :data:`MIN_SHIFTED` frames depart from the scan's
    common offset by more than half :data:`STAGE_SHIFT_PX` (and :data:`SIGNIFICANCE` standard
    errors) or none by more than it; frames with fewer than :data:`MIN_AGREEING_FOCI` foci agreeing
    (or than the model's bright foci per frame, where it has fewer) are not judged."""
    motion = frame_motion(analysis, vertices_px)
    shifts = motion.shift_px
    enough = min(MIN_AGREEING_FOCI, int(bright_foci(analysis).sum(axis=1).max()))  # what the design gives a frame
    known = np.flatnonzero(np.isfinite(shifts).all(axis=1) & (motion.foci >= enough))
    if len(known) < MIN_FRAMES:
        return None
    beyond = np.linalg.norm(shifts[known] - np.median(shifts[known], axis=0), axis=1)
    noise = SIGNIFICANCE * motion.shift_se_px[known]
    moved = beyond > np.maximum(STAGE_SHIFT_PX / 2, noise)
    if not np.any(beyond > np.maximum(STAGE_SHIFT_PX, noise)) or np.sum(moved) < MIN_SHIFTED:
        return None
    apart = float(np.max(np.linalg.norm(shifts[known, None] - shifts[None, known], axis=-1)))
    worst = known[np.argsort(np.where(moved, beyond, -1.0))[::-1][: min(6, int(np.sum(moved)))]]
    return (
        f"the foci of whole frames are displaced together from the model, differently from frame to frame: up to "
        f"{apart:.2f} px ({apart * pixel_um:.0f} µm on the sensor) apart, {int(np.sum(moved))} "
        f"of {len(known)} frames more than {STAGE_SHIFT_PX / 2:.2g} px from the scan's common offset (most: "
        f"{', '.join(analysis.files[i] for i in worst)}): the source was not where positions.csv says (stage "
        f"backlash or a position error), which no effect of the optics does"
    )


def spread_rate_per_mm(design: SystemDesign, z_mm: np.ndarray) -> np.ndarray:
    """d ln(1 + m)/dz (per mm) at each object-space depth ``z_mm``: how fast the spread of the
    lenslets' foci changes with the source's depth (m the chief-ray magnification; central
    difference over ±10 µm)."""
    step = 0.01

    def spread(z: float) -> float:
        return np.log1p(first_order.chief_ray_magnification(design, first_order.object_z_to_height_mm(design, z)))

    return np.array([(spread(z + step) - spread(z - step)) / (2 * step) for z in np.asarray(z_mm, float)])


def stage_z_scale(analysis: ResidualAnalysis, spread_rate: np.ndarray) -> str | None:
    """A warning when the frames' depth errors δz (from their foci's spread, ``spread_rate`` (N,)
    per mm from :func:`spread_rate_per_mm`) grow with the recorded depth (module docstring): the
    slope of δz on z, when it is at least :data:`Z_SCALE_MIN` and :data:`SIGNIFICANCE` standard
    errors; None otherwise, or when the scan holds one depth."""
    motion = frame_motion(analysis)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth_error = motion.expansion / np.asarray(spread_rate, float)
    known = np.flatnonzero(np.isfinite(depth_error))
    z = analysis.positions_mm[known, 2]
    if len(known) < MIN_FRAMES or len(np.unique(np.round(z, 6))) < 2:
        return None
    design = np.column_stack([np.ones(len(known)), z])
    (offset, scale), *_ = np.linalg.lstsq(design, depth_error[known], rcond=None)
    scatter = depth_error[known] - design @ np.array([offset, scale])
    scale_se = np.sqrt(float(np.sum(scatter**2)) / max(len(known) - 2, 1) / float(np.sum((z - z.mean()) ** 2)))
    if abs(scale) < Z_SCALE_MIN or abs(scale) < SIGNIFICANCE * scale_se:
        return None
    return (
        f"the foci's spread changes with depth as if the source's z steps were {1 + scale:.3f} ± {scale_se:.3f} "
        f"times the recorded ones (a z scale error of {scale:+.1%}; the depth errors δz = {scale:+.3f}·z "
        f"{offset:+.3f} mm over {len(known)} frames): the stage's z axis is not calibrated (pitch, steps per mm), "
        f"which no effect of the optics does"
    )


def lateral_jacobians(analysis: ResidualAnalysis) -> dict[float, np.ndarray]:
    """Per recorded depth (mm), the model's foci's motion on the sensor per mm of source x and y:
    the 2 × 2 matrix J (row, col px per x, y mm) shared by the lenslets, fitted as m_ij = α_j +
    J·(x_i, y_i) over the frames at that depth (α_j one per lenslet); depths with fewer than three
    frames or positions on one line are left out."""
    out: dict[float, np.ndarray] = {}
    centroids = analysis.model.centroid_px
    xy = np.asarray(analysis.positions_mm, float)[:, :2]
    z = np.round(np.asarray(analysis.positions_mm, float)[:, 2], 6)
    for depth in np.unique(z):
        frames = np.flatnonzero(z == depth)
        rows_p, rows_m = [], []
        for j in range(centroids.shape[1]):
            known = frames[np.isfinite(centroids[frames, j]).all(axis=1)]
            if len(known) < 3:
                continue
            rows_p.append(xy[known] - xy[known].mean(axis=0))
            rows_m.append(centroids[known, j] - centroids[known, j].mean(axis=0))
        if not rows_p:
            continue
        p, m = np.concatenate(rows_p), np.concatenate(rows_m)
        if np.linalg.matrix_rank(p) < 2:
            continue
        solution, *_ = np.linalg.lstsq(p, m, rcond=None)  # m = p @ Jᵀ
        out[float(depth)] = solution.T
    return out


def stage_xy_map(analysis: ResidualAnalysis, vertices_px: np.ndarray | None = None) -> str | None:
    """A warning when the frames' source errors grow linearly with the recorded x, y (module
    docstring): each frame's translation (:func:`frame_motion`) carried back to the source as
    δp = J⁻¹·t, regressed δp = c + A·p over the frames judged (as :func:`stage_errors` judges
    them); the rotation (A₂₁ − A₁₂)/2 and the scales A₁₁, A₂₂ named when beyond
    :data:`XY_ROTATION_MIN_DEG` / :data:`XY_SCALE_MIN` and :data:`SIGNIFICANCE` standard errors;
    None otherwise, or when the positions do not span x and y."""
    motion = frame_motion(analysis, vertices_px)
    jacobians = lateral_jacobians(analysis)
    enough = min(MIN_AGREEING_FOCI, int(bright_foci(analysis).sum(axis=1).max()))
    z = np.round(np.asarray(analysis.positions_mm, float)[:, 2], 6)
    known = [
        i
        for i in range(len(z))
        if np.isfinite(motion.shift_px[i]).all() and motion.foci[i] >= enough and float(z[i]) in jacobians
    ]
    if len(known) < MIN_FRAMES:
        return None
    p = np.asarray(analysis.positions_mm, float)[known, :2]
    if np.linalg.matrix_rank(p - p.mean(axis=0)) < 2:
        return None
    error = np.array([np.linalg.solve(jacobians[float(z[i])], motion.shift_px[i]) for i in known])  # δp, mm
    design = np.column_stack([np.ones(len(known)), p])
    solution, *_ = np.linalg.lstsq(design, error, rcond=None)  # (3, 2): δp = c + A·p, A = solution[1:].T
    a = solution[1:].T
    dof = max(len(known) - 3, 1)
    scatter = np.sum((error - design @ solution) ** 2, axis=0) / dof  # per component of δp
    inverse = np.linalg.inv(design.T @ design)
    se = np.sqrt(np.outer(scatter, np.diag(inverse)[1:]))  # se[k, l] of A[k, l]
    rotation = 0.5 * (a[1, 0] - a[0, 1])
    rotation_se = 0.5 * float(np.hypot(se[1, 0], se[0, 1]))
    found = []
    if abs(np.degrees(rotation)) >= XY_ROTATION_MIN_DEG and abs(rotation) >= SIGNIFICANCE * rotation_se:
        found.append(
            f"rotated by {np.degrees(rotation):+.2f} ± {np.degrees(rotation_se):.3f}° (from x towards y) against "
            "the design's"
        )
    for k, axis in enumerate("xy"):
        if abs(a[k, k]) >= XY_SCALE_MIN and abs(a[k, k]) >= SIGNIFICANCE * se[k, k]:
            found.append(f"its {axis} steps {1 + a[k, k]:.3f} ± {se[k, k]:.3f} times the recorded ones")
    if not found:
        return None
    return (
        f"the frames' source errors grow with the recorded position as if the stage's x, y axes were "
        f"{' and '.join(found)} (over {len(known)} frames, the errors carried back to the source through the "
        f"model's foci): the stage's lateral axes are not aligned or calibrated against the sensor, which no "
        f"effect of the optics does"
    )
