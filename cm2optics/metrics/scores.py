"""Detection and localisation scores (Supplement 1 of the paper), and the global threshold.

With TP matched pairs, FP unmatched detections and FN unmatched true emitters:

- recall = TP / (TP + FN), precision = TP / (TP + FP),
- F1 = 2·TP / (2·TP + FP + FN), Jaccard index = TP / (TP + FP + FN),
- lateral RMSE = √(mean over TP of Δx² + Δy²), axial RMSE = √(mean over TP of Δz²) (µm).

Empty sets are defined, never NaN: with no true emitters recall is 1 (nothing was missed), with
no detections precision is 1 (nothing false was claimed), and F1 and Jaccard are 1 when both
sets are empty (0 whenever something exists and nothing matched); with no true positive the
RMSEs are ``None`` (JSON ``null``): there is no localisation error to measure.

The global threshold that binarises a reconstruction is, unless given, the one that maximises
F1 pooled over a validation set (:func:`f1_optimal_threshold`): a log-spaced sweep between
1e-3 and 0.95 of the set's largest value, refined around the best candidate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.metrics.detect import detect_emitters
from cm2optics.metrics.match import Matching, match_emitters

__all__ = ["Evaluation", "MatchOptions", "evaluate_volume", "f1_optimal_threshold", "pooled_scores", "scores"]

SCORE_KEYS = ("recall", "precision", "f1", "jaccard", "rmse_lateral_um", "rmse_axial_um", "n_true", "n_detected")
#: What a report shows: the scores and the match counts behind them.
REPORTED_KEYS = (*SCORE_KEYS, "n_tp", "n_fp", "n_fn")


def scores(n_tp: int, n_fp: int, n_fn: int, offsets_um: np.ndarray | None = None) -> dict[str, float | int | None]:
    """The scores of one set of counts and the (TP, 3) offsets (dx, dy, dz) µm of its pairs."""
    n_true, n_det = n_tp + n_fn, n_tp + n_fp
    recall = n_tp / n_true if n_true else 1.0
    precision = n_tp / n_det if n_det else 1.0
    both = 2 * n_tp + n_fp + n_fn
    f1 = 2 * n_tp / both if both else 1.0
    union = n_tp + n_fp + n_fn
    jaccard = n_tp / union if union else 1.0
    rmse_lat = rmse_ax = None
    if offsets_um is not None and len(offsets_um) and n_tp:
        offsets_um = np.asarray(offsets_um, dtype=np.float64).reshape(-1, 3)
        rmse_lat = float(math.sqrt(np.mean(offsets_um[:, 0] ** 2 + offsets_um[:, 1] ** 2)))
        rmse_ax = float(math.sqrt(np.mean(offsets_um[:, 2] ** 2)))
    return {
        "recall": float(recall),
        "precision": float(precision),
        "f1": float(f1),
        "jaccard": float(jaccard),
        "rmse_lateral_um": rmse_lat,
        "rmse_axial_um": rmse_ax,
        "n_true": int(n_true),
        "n_detected": int(n_det),
        "n_tp": int(n_tp),
        "n_fp": int(n_fp),
        "n_fn": int(n_fn),
    }


@dataclass(frozen=True)
class MatchOptions:
    """How detections are made and matched.

    gate_factor: a pair may match within gate_factor × the true diameter (paper: 2).
    min_gate_um: floor of the gate, µm (points of zero diameter still match within it);
        ``None``: the grid's coarsest voxel pitch.
    connectivity: 6, 18 or 26 neighbours for the connected components.
    min_voxels: smaller components are not detections.
    """

    gate_factor: float = 2.0
    min_gate_um: float | None = None
    connectivity: int = 26
    min_voxels: int = 1

    def floor_um(self, grid: VolumeGrid) -> float:
        return float(max(grid.voxel_um)) if self.min_gate_um is None else float(self.min_gate_um)


@dataclass(frozen=True)
class Evaluation:
    """One reconstruction against its truth: the threshold, the emitters, the matching, scores."""

    threshold: float
    truth: Emitters
    detected: Emitters
    matching: Matching
    grid: VolumeGrid
    metrics: dict[str, Any] = field(default_factory=dict)


def evaluate_volume(
    recon: np.ndarray,
    grid: VolumeGrid,
    truth: Emitters,
    threshold: float,
    options: MatchOptions = MatchOptions(),
) -> Evaluation:
    """Binarise ``recon`` at ``threshold``, detect, match to ``truth`` and score."""
    detected = detect_emitters(recon, grid, threshold, connectivity=options.connectivity, min_voxels=options.min_voxels)
    matching = match_emitters(truth, detected, gate_factor=options.gate_factor, min_gate_um=options.floor_um(grid))
    metrics = scores(matching.n_tp, matching.n_fp, matching.n_fn, matching.offset_um)
    return Evaluation(float(threshold), truth, detected, matching, grid, metrics)


def pooled_scores(evaluations: Sequence[Evaluation]) -> dict[str, Any]:
    """Scores of several evaluations pooled (counts and pairs summed over volumes)."""
    tp = sum(e.matching.n_tp for e in evaluations)
    fp = sum(e.matching.n_fp for e in evaluations)
    fn = sum(e.matching.n_fn for e in evaluations)
    offsets = [e.matching.offset_um for e in evaluations if len(e.matching.offset_um)]
    return scores(tp, fp, fn, np.concatenate(offsets) if offsets else None)


def f1_optimal_threshold(
    pairs: Sequence[tuple[np.ndarray, VolumeGrid, Emitters]],
    options: MatchOptions = MatchOptions(),
    *,
    n_coarse: int = 20,
    n_fine: int = 8,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[float, dict[str, Any]]:
    """The global threshold maximising F1 pooled over a validation set of (recon, grid, truth);
    returns it and the sweep (``thresholds``, ``f1``). Ties go to the lower threshold."""
    if not pairs:
        raise ValueError("the validation set is empty: give at least one (reconstruction, truth) pair")
    vmax = max(float(np.max(r)) if np.size(r) else 0.0 for r, _, _ in pairs)
    if not math.isfinite(vmax) or vmax <= 0:
        return 0.0, {
            "thresholds": [0.0],
            "f1": [pooled_scores([evaluate_volume(r, g, t, 0.0, options) for r, g, t in pairs])["f1"]],
        }
    total = n_coarse + n_fine
    done = [0]

    def f1_at(threshold: float) -> float:
        value = pooled_scores([evaluate_volume(r, g, t, threshold, options) for r, g, t in pairs])["f1"]
        done[0] += 1
        if progress:
            progress(done[0], total)
        return value

    coarse = np.geomspace(1e-3 * vmax, 0.95 * vmax, n_coarse)
    values = [f1_at(t) for t in coarse]
    best = int(np.argmax(values))
    low = coarse[max(best - 1, 0)]
    high = coarse[min(best + 1, len(coarse) - 1)]
    fine = np.geomspace(low, high, n_fine + 2)[1:-1]
    fine_values = [f1_at(t) for t in fine]
    thresholds = np.concatenate([coarse, fine])
    f1s = np.concatenate([values, fine_values])
    order = np.argsort(thresholds)
    thresholds, f1s = thresholds[order], f1s[order]
    pick = int(np.flatnonzero(f1s == f1s.max())[0])
    return float(thresholds[pick]), {"thresholds": thresholds.tolist(), "f1": f1s.tolist()}
