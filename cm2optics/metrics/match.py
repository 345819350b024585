"""Gated Hungarian matching of detected to true emitters.

A detection may pair with a true emitter only when their 3-D distance (µm, physical
coordinates, so anisotropic voxels need no special case) is at most the true emitter's gate,
``gate_factor × diameter`` (2× in the paper), floored at ``min_gate_um``. The gate is applied
*before* the assignment: impossible pairs cost more than every possible pairing together, so
:func:`scipy.optimize.linear_sum_assignment` first maximises the number of gated pairs, then
minimises their summed distance. The gated pairs form a sparse bipartite graph; each of its
connected components is solved on its own (exactly the same optimum as one global assignment,
but thousands of emitters cost milliseconds instead of a dense N × M matrix).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cm2optics.formats.emitters import Emitters

__all__ = ["Matching", "gates_um", "match_emitters"]


@dataclass(frozen=True)
class Matching:
    """Pairs (true index, detected index), their distances, and the offsets detected − true (µm).

    true_index, detected_index: (P,) int arrays of matched pairs, sorted by true index.
    distance_um: (P,) 3-D distances. offset_um: (P, 3) as (dx, dy, dz), µm.
    n_true, n_detected: sizes of the two sets.
    """

    true_index: np.ndarray
    detected_index: np.ndarray
    distance_um: np.ndarray
    offset_um: np.ndarray
    n_true: int
    n_detected: int

    @property
    def n_tp(self) -> int:
        return len(self.true_index)

    @property
    def n_fn(self) -> int:
        return self.n_true - self.n_tp

    @property
    def n_fp(self) -> int:
        return self.n_detected - self.n_tp

    def true_matched(self) -> np.ndarray:
        """(n_true,) bool: this true emitter was found."""
        out = np.zeros(self.n_true, bool)
        out[self.true_index] = True
        return out

    def detected_matched(self) -> np.ndarray:
        """(n_detected,) bool: this detection is a true positive."""
        out = np.zeros(self.n_detected, bool)
        out[self.detected_index] = True
        return out

    def partner_of_detection(self) -> np.ndarray:
        """(n_detected,) index of each detection's true emitter, −1 for a false positive."""
        out = np.full(self.n_detected, -1, np.int64)
        out[self.detected_index] = self.true_index
        return out


def gates_um(truth: Emitters, gate_factor: float = 2.0, min_gate_um: float = 0.0) -> np.ndarray:
    """Per true emitter, the largest distance (µm) at which a detection may match it."""
    if not np.isfinite(gate_factor) or gate_factor <= 0:
        raise ValueError(f"gate_factor = {gate_factor}: must be a finite number > 0")
    if not np.isfinite(min_gate_um) or min_gate_um < 0:
        raise ValueError(f"min_gate_um = {min_gate_um}: must be a finite number ≥ 0")
    return np.maximum(gate_factor * truth.diameter_um, min_gate_um)


def match_emitters(
    truth: Emitters, detected: Emitters, *, gate_factor: float = 2.0, min_gate_um: float = 0.0
) -> Matching:
    """Match ``detected`` to ``truth`` (see the module docstring)."""
    n_true, n_det = len(truth), len(detected)
    gate = gates_um(truth, gate_factor, min_gate_um)
    empty = Matching(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), n_true, n_det)
    if n_true == 0 or n_det == 0 or not np.any(gate > 0):
        return empty
    t_xyz = np.stack([truth.x_um, truth.y_um, truth.z_um], axis=1)
    d_xyz = np.stack([detected.x_um, detected.y_um, detected.z_um], axis=1)
    pairs = cKDTree(t_xyz).sparse_distance_matrix(cKDTree(d_xyz), max_distance=float(gate.max()), output_type="ndarray")
    ti, di, dist = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), pairs["v"].astype(np.float64)
    ok = dist <= gate[ti] * (1 + 1e-12)
    ti, di, dist = ti[ok], di[ok], dist[ok]
    if len(ti) == 0:
        return empty
    # connected components of the bipartite gate graph (true nodes 0..n_true-1, detections after)
    n = n_true + n_det
    graph = coo_matrix((np.ones(len(ti)), (ti, n_true + di)), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    edge_component = component[ti]
    order = np.argsort(edge_component, kind="stable")
    ti, di, dist, edge_component = ti[order], di[order], dist[order], edge_component[order]
    bounds = np.flatnonzero(np.diff(edge_component)) + 1
    out_t, out_d = [], []
    for start, stop in zip(np.r_[0, bounds], np.r_[bounds, len(ti)], strict=True):
        et, ed, ev = ti[start:stop], di[start:stop], dist[start:stop]
        if stop - start == 1:
            out_t.append(et)
            out_d.append(ed)
            continue
        rows, r_index = np.unique(et, return_inverse=True)
        cols, c_index = np.unique(ed, return_inverse=True)
        impossible = float(ev.sum()) + 1.0 + float(gate.max()) * (len(rows) + len(cols))
        cost = np.full((len(rows), len(cols)), impossible)
        cost[r_index, c_index] = ev
        r, c = linear_sum_assignment(cost)
        good = cost[r, c] < impossible
        out_t.append(rows[r[good]])
        out_d.append(cols[c[good]])
    true_index = np.concatenate(out_t)
    detected_index = np.concatenate(out_d)
    order = np.argsort(true_index, kind="stable")
    true_index, detected_index = true_index[order], detected_index[order]
    offset = d_xyz[detected_index] - t_xyz[true_index]
    return Matching(true_index, detected_index, np.linalg.norm(offset, axis=1), offset, n_true, n_det)
