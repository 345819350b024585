"""Scores broken down as in the paper's Fig. 6, and recall/precision maps over the field.

Per-emitter breakdowns (lateral distance from the centre, depth, size) put every true emitter in
the bin of its own attribute and every detection in the bin of its matched true emitter's
attribute (a false positive: its own, the size being its component's equivalent diameter);
values beyond the outermost edges count in the outermost bins (nothing is dropped), so
that a bin's recall is TP/(TP + FN) over the true emitters in it and its precision TP/(TP + FP)
over the detections in it, with the same TP. RMSEs are over the TP pairs of the bin. Over
several volumes a bin reports the pooled scores and the mean ± sd of the per-volume scores
(bins a volume leaves empty do not count towards its mean).

The density breakdown is per volume (a volume has one density): volumes are grouped by their
density bin, and each bin reports pooled and mean ± sd scores.

Maps: the field is cut into non-overlapping square patches (250 µm in the paper); a patch's
recall is TP/n_true over the true emitters whose centre lies in it, its precision TP/n_detected
over the detections in it. Matching is global, so pairs that straddle a patch edge count (the
paper pads its patches to the gate for the same reason). A patch with no true emitter has no
recall: NaN in the map array, drawn blank.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cm2optics.metrics.scores import Evaluation, scores

__all__ = [
    "BREAKDOWNS",
    "Breakdown",
    "breakdown",
    "density_breakdown",
    "detection_maps",
    "emitter_attribute",
    "merge_evaluations",
]


@dataclass(frozen=True)
class Breakdown:
    """A per-emitter breakdown: its name, attribute, unit and bin edges."""

    name: str
    label: str
    unit: str
    edges: tuple[float, ...]


#: The paper's bins (Fig. 6): 7 lateral bins of 0.5 mm, 9 depth bins, 7 size bins of 2 µm.
BREAKDOWNS = {
    "lateral_mm": Breakdown("lateral_mm", "distance from the centre", "mm", tuple(np.arange(0, 3.5 + 1e-9, 0.5))),
    "depth_um": Breakdown("depth_um", "depth z", "µm", (-400, -350, -250, -150, -50, 50, 150, 250, 350, 400)),
    "size_um": Breakdown("size_um", "diameter", "µm", tuple(np.arange(7, 21 + 1e-9, 2.0))),
}
#: The paper's nine density ranges [10:10:100] (emitters per mm², Fig. 6b); the last is closed.
DENSITY_EDGES = tuple(np.arange(10, 100 + 1e-9, 10.0))


def emitter_attribute(name: str, x_um: np.ndarray, y_um: np.ndarray, z_um: np.ndarray, d_um: np.ndarray) -> np.ndarray:
    if name == "lateral_mm":
        return np.hypot(x_um, y_um) / 1000.0
    if name == "depth_um":
        return np.asarray(z_um, float)
    if name == "size_um":
        return np.asarray(d_um, float)
    raise ValueError(f"unknown breakdown {name!r}: use one of {', '.join(BREAKDOWNS)}")


def _attributes(evaluation: Evaluation, name: str) -> tuple[np.ndarray, np.ndarray]:
    t, d = evaluation.truth, evaluation.detected
    true_attr = emitter_attribute(name, t.x_um, t.y_um, t.z_um, t.diameter_um)
    det_attr = emitter_attribute(name, d.x_um, d.y_um, d.z_um, d.diameter_um)
    partner = evaluation.matching.partner_of_detection()
    matched = partner >= 0
    det_attr = det_attr.copy()
    det_attr[matched] = true_attr[partner[matched]]
    return true_attr, det_attr


def _bin_index(values: np.ndarray, edges: np.ndarray, clip: bool = False) -> np.ndarray:
    """Bin of each value; the last bin is closed on the right. Outside the edges: −1, or with
    ``clip`` the outermost bin."""
    index = np.searchsorted(edges, values, side="right") - 1
    index[values == edges[-1]] = len(edges) - 2
    if clip:
        return np.clip(index, 0, len(edges) - 2)
    index[(values < edges[0]) | (values > edges[-1])] = -1
    return index


def _bin_counts(evaluation: Evaluation, name: str, edges: np.ndarray) -> list[dict[str, Any]]:
    true_attr, det_attr = _attributes(evaluation, name)
    tb, db = _bin_index(true_attr, edges, clip=True), _bin_index(det_attr, edges, clip=True)
    m = evaluation.matching
    true_found = m.true_matched()
    rows = []
    for b in range(len(edges) - 1):
        in_t = tb == b
        pairs = tb[m.true_index] == b
        n_tp = int(np.sum(true_found & in_t))
        n_fn = int(np.sum(in_t)) - n_tp
        n_fp = int(np.sum(db == b)) - n_tp
        rows.append({"tp": n_tp, "fp": n_fp, "fn": n_fn, "offsets": m.offset_um[pairs]})
    return rows


def _summary(counts: list[dict[str, Any]]) -> dict[str, Any]:
    tp = sum(c["tp"] for c in counts)
    fp = sum(c["fp"] for c in counts)
    fn = sum(c["fn"] for c in counts)
    offsets = [c["offsets"] for c in counts if len(c["offsets"])]
    return scores(tp, fp, fn, np.concatenate(offsets) if offsets else None)


def _spread(per_volume: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean and sd over volumes of recall, precision, F1, Jaccard and RMSEs; a volume counts for
    recall only if it has true emitters, for precision only if it has detections, for the RMSEs
    only if it has true positives (no vacuous 1s in the means)."""
    needs = {"recall": "n_true", "precision": "n_detected", "rmse_lateral_um": "n_tp", "rmse_axial_um": "n_tp"}
    out: dict[str, Any] = {}
    for key in ("recall", "precision", "f1", "jaccard", "rmse_lateral_um", "rmse_axial_um"):
        count = needs.get(key)
        values = [v[key] for v in per_volume if v[key] is not None and (count is None or v.get(count, 1) > 0)]
        out[f"{key}_mean"] = float(np.mean(values)) if values else None
        out[f"{key}_sd"] = float(np.std(values)) if len(values) > 1 else (0.0 if values else None)
    return out


def breakdown(
    evaluations: Evaluation | Sequence[Evaluation], name: str, edges: Sequence[float] | None = None
) -> list[dict[str, Any]]:
    """Scores per bin of ``name`` (``lateral_mm``, ``depth_um`` or ``size_um``) over one or
    several evaluations: one dict per bin with ``low``, ``high``, the pooled scores and, over
    several volumes, ``*_mean`` / ``*_sd`` of the per-volume scores (volumes with nothing in the
    bin left out)."""
    if isinstance(evaluations, Evaluation):
        evaluations = [evaluations]
    if name not in BREAKDOWNS:
        raise ValueError(f"unknown breakdown {name!r}: use one of {', '.join(BREAKDOWNS)}")
    edges_array = np.asarray(BREAKDOWNS[name].edges if edges is None else edges, dtype=float)
    if edges_array.ndim != 1 or len(edges_array) < 2 or np.any(np.diff(edges_array) <= 0):
        raise ValueError(f"{name} bin edges must increase strictly (got {list(edges_array)})")
    per_volume = [_bin_counts(e, name, edges_array) for e in evaluations]
    rows = []
    for b in range(len(edges_array) - 1):
        counts = [v[b] for v in per_volume]
        row = {"low": float(edges_array[b]), "high": float(edges_array[b + 1]), **_summary(counts)}
        present = [_summary([c]) for c in counts if c["tp"] + c["fp"] + c["fn"] > 0]
        row.update(_spread(present))
        row["n_volumes"] = len(present)
        rows.append(row)
    return rows


def density_breakdown(
    evaluations: Sequence[Evaluation], densities_per_mm2: Sequence[float], edges: Sequence[float] = DENSITY_EDGES
) -> list[dict[str, Any]]:
    """Scores of volumes grouped by their density (emitters/mm²), one dict per density bin."""
    if len(evaluations) != len(densities_per_mm2):
        raise ValueError(f"{len(evaluations)} evaluations but {len(densities_per_mm2)} densities")
    edges_array = np.asarray(edges, float)
    index = _bin_index(np.asarray(densities_per_mm2, float), edges_array)
    rows = []
    for b in range(len(edges_array) - 1):
        members = [e for e, i in zip(evaluations, index, strict=True) if i == b]
        counts = [
            {"tp": e.matching.n_tp, "fp": e.matching.n_fp, "fn": e.matching.n_fn, "offsets": e.matching.offset_um}
            for e in members
        ]
        row = {"low": float(edges_array[b]), "high": float(edges_array[b + 1]), **_summary(counts)}
        row.update(_spread([e.metrics for e in members]))
        row["n_volumes"] = len(members)
        rows.append(row)
    return rows


def merge_evaluations(evaluations: Sequence[Evaluation]) -> Evaluation:
    """Several volumes on the same grid as one evaluation (emitters and pairs concatenated), for
    maps and pooled breakdowns over a test set."""
    from cm2optics.formats.emitters import EMITTER_COLUMNS, Emitters
    from cm2optics.metrics.match import Matching

    if not evaluations:
        raise ValueError("nothing to merge: no evaluations")
    truth = Emitters(*(np.concatenate([getattr(e.truth, c) for e in evaluations]) for c in EMITTER_COLUMNS))
    detected = Emitters(*(np.concatenate([getattr(e.detected, c) for e in evaluations]) for c in EMITTER_COLUMNS))
    t_off = np.cumsum([0] + [e.matching.n_true for e in evaluations])[:-1]
    d_off = np.cumsum([0] + [e.matching.n_detected for e in evaluations])[:-1]
    m = Matching(
        np.concatenate([e.matching.true_index + o for e, o in zip(evaluations, t_off, strict=True)]),
        np.concatenate([e.matching.detected_index + o for e, o in zip(evaluations, d_off, strict=True)]),
        np.concatenate([e.matching.distance_um for e in evaluations]),
        np.concatenate([e.matching.offset_um for e in evaluations]).reshape(-1, 3),
        len(truth),
        len(detected),
    )
    return Evaluation(
        evaluations[0].threshold, truth, detected, m, evaluations[0].grid, scores(m.n_tp, m.n_fp, m.n_fn, m.offset_um)
    )


def detection_maps(evaluation: Evaluation, patch_um: float = 250.0) -> dict[str, Any]:
    """Recall and precision per non-overlapping ``patch_um`` patch of the field: ``recall``,
    ``precision`` (ny, nx) arrays (NaN: nothing to measure), ``n_true``, ``n_detected`` counts
    and the patch ``x_edges_um`` / ``y_edges_um``."""
    if not np.isfinite(patch_um) or patch_um <= 0:
        raise ValueError(f"patch_um = {patch_um}: must be a finite number > 0")
    grid = evaluation.grid
    half_y = grid.shape[1] * grid.voxel_um[1] / 2.0
    half_x = grid.shape[2] * grid.voxel_um[2] / 2.0
    ny, nx = max(int(np.ceil(2 * half_y / patch_um)), 1), max(int(np.ceil(2 * half_x / patch_um)), 1)
    y_edges = -ny * patch_um / 2.0 + patch_um * np.arange(ny + 1)
    x_edges = -nx * patch_um / 2.0 + patch_um * np.arange(nx + 1)

    def counts(x: np.ndarray, y: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        iy = np.clip(np.searchsorted(y_edges, y, side="right") - 1, 0, ny - 1)
        ix = np.clip(np.searchsorted(x_edges, x, side="right") - 1, 0, nx - 1)
        total = np.zeros((ny, nx))
        good = np.zeros((ny, nx))
        np.add.at(total, (iy, ix), 1.0)
        np.add.at(good, (iy, ix), hit.astype(float))
        return total, good

    t, d, m = evaluation.truth, evaluation.detected, evaluation.matching
    n_true, tp_true = counts(t.x_um, t.y_um, m.true_matched())
    n_det, tp_det = counts(d.x_um, d.y_um, m.detected_matched())
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = np.where(n_true > 0, tp_true / np.where(n_true > 0, n_true, 1), np.nan)
        precision = np.where(n_det > 0, tp_det / np.where(n_det > 0, n_det, 1), np.nan)
    return {
        "patch_um": float(patch_um),
        "x_edges_um": x_edges,
        "y_edges_um": y_edges,
        "recall": recall,
        "precision": precision,
        "n_true": n_true.astype(int),
        "n_detected": n_det.astype(int),
    }
