"""Held-out checks in pixels: how well the calibration nodes predict a node left out, as the
sensor sees it (the node's own whole-pixel frame around each focus, not a resampled crop).

For every held-out node (interior, seeded), each lenslet's node PSF is predicted by linear
interpolation between its two neighbours along x, y and z (their mean, as
:func:`cm2optics.lsv.validate.validate_model`), placed at the node's exact sub-pixel focus
(Keys shift of a whole-pixel crop, or the ePSF sampled at the pixel centres) and compared with
the frame. The error splits into three measured parts:

* ``at_node_full``: the node's own registered crop placed back: the registration and placement
  floor, i.e. the sub-pixel **phase** error (≈ 0 for a synthetic ePSF, large for whole pixels
  when the foci are ≈ 1 px wide);
* ``interpolated_full`` − ``at_node_full``: the PSF **shape change between nodes** that linear
  interpolation misses (full rank);
* ``interpolated_rank`` − ``interpolated_full``: the **low rank** (a K-term basis from the
  nodes that are not held out).

NMSE per node: Σ_j ‖p_j − y_j‖² / Σ_j ‖y_j‖²; the mean over held-out nodes is reported. The
``at_node`` figures need the held-out nodes' own crops (a basis estimated without them has none:
ignore them then).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from cm2optics.lsv.decompose import decompose
from cm2optics.lsv.focal_surface import FocalSurface
from cm2optics.lsv.interpolate import axis_coordinate, tent_pairs
from cm2optics.lsv.rotation import AzimuthTurn
from cm2optics.lsv.warp import displacement_blend

__all__ = [
    "heldout_nodes",
    "leave_one_out_pixels",
    "predicted_nodes_nmse",
    "projector",
    "turn_check",
    "undithered_axis",
]


def undithered_axis(values_mm: np.ndarray, px_per_mm: float, within_px: float) -> np.ndarray:
    """Indices of the sorted axis values ``values_mm`` that are nodes, not dithers: each value more
    than ``within_px`` (at ``px_per_mm`` of focus travel) past the last node kept."""
    kept = [0]
    for i in range(1, len(values_mm)):
        if (values_mm[i] - values_mm[kept[-1]]) * px_per_mm > within_px:
            kept.append(i)
    return np.asarray(kept)


def heldout_nodes(grid_index: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` interior nodes (seeded), as rows of ``grid_index`` (N, 3)."""
    gi = np.asarray(grid_index)
    shape = gi.max(axis=0) + 1
    ok = np.ones(len(gi), bool)
    for axis, size in enumerate(shape):
        if size >= 3:
            ok &= (gi[:, axis] > 0) & (gi[:, axis] < size - 1)
    candidates = np.nonzero(ok)[0]
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(candidates, size=min(n, len(candidates)), replace=False))


def _place(patch: np.ndarray, eps: np.ndarray, S: int) -> np.ndarray:
    from cm2optics.lsv.epsf import place_epsf
    from cm2optics.lsv.sparse import _shift_patch

    return place_epsf(patch, (eps[0], eps[1]), S) if S > 1 else _shift_patch(patch, (eps[0], eps[1]))


def _frame_errors(prediction: np.ndarray, frame: np.ndarray, eps: np.ndarray, S: int) -> tuple[np.ndarray, np.ndarray]:
    """Per lenslet ‖p_j − y_j‖² and ‖y_j‖² (J,) of the PSFs ``prediction`` (J, h·S, w·S) placed at
    the foci's sub-pixel fractions ``eps`` (J, 2) against the node's ``frame`` (J, h+3, w+3)."""
    placed = np.stack([_place(prediction[j], eps[j], S) for j in range(len(prediction))])
    y = np.asarray(frame, np.float64)
    return ((placed - y) ** 2).sum(axis=(1, 2)), (y**2).sum(axis=(1, 2))


def _frame_nmse(prediction: np.ndarray, frame: np.ndarray, eps: np.ndarray, S: int) -> float:
    """Σ_j ‖p_j − y_j‖² / Σ_j ‖y_j‖² of the PSFs ``prediction`` (J, h·S, w·S) placed at the foci's
    sub-pixel fractions ``eps`` (J, 2) against the node's ``frame`` (J, h+3, w+3)."""
    error, norm = _frame_errors(prediction, frame, eps, S)
    return float(error.sum() / max(norm.sum(), 1e-300))


#: A lenslet's focus counts as lit in a node's frame (for the per-lenslet figures) where its
#: energy is above this share of the node's brightest focus.
LIT_SHARE = 1e-6


def projector(basis: np.ndarray | list[np.ndarray], terms: int | None = None):
    """x (J, h, w) → its orthogonal projection on ``basis``: one basis of focus arrays (K, J, h, w)
    (its first ``terms``), or per-lenslet bases ``[(K_j, h, w)]`` (each lenslet's first ``terms``
    projected on its own), orthonormal, in float64."""
    if isinstance(basis, np.ndarray):
        B = basis[:terms].reshape(len(basis[:terms]), -1).astype(np.float64)

        def project(x: np.ndarray) -> np.ndarray:
            return (B.T @ (B @ x.reshape(-1).astype(np.float64))).reshape(x.shape)

        return project
    blocks = [b[:terms].reshape(len(b[:terms]), -1).astype(np.float64) for b in basis]

    def project_lenslets(x: np.ndarray) -> np.ndarray:
        out = np.zeros(x.shape)
        for j, B in enumerate(blocks):
            out[j] = (B.T @ (B @ x[j].reshape(-1).astype(np.float64))).reshape(x.shape[1:])
        return out

    return project_lenslets


def _summary(errors: list[tuple[np.ndarray, np.ndarray]], name: str) -> dict[str, Any]:
    """Per-node NMSE (Σ_j over the lenslets), its mean and median, and each lenslet's own mean
    and median over the nodes where it is lit (:data:`LIT_SHARE`), keys prefixed ``name``."""
    per_node = [float(e.sum() / max(n.sum(), 1e-300)) for e, n in errors]
    J = len(errors[0][0]) if errors else 0
    lenslet: list[list[float]] = [[] for _ in range(J)]
    for e, n in errors:
        for j in np.flatnonzero(n > LIT_SHARE * n.max()):
            lenslet[j].append(float(e[j] / n[j]))
    return {
        name: float(np.mean(per_node)) if per_node else None,
        f"{name}_per_node": per_node,
        f"{name}_median": float(np.median(per_node)) if per_node else None,
        f"{name}_per_lenslet": [float(np.mean(v)) if v else None for v in lenslet],
        f"{name}_per_lenslet_median": [float(np.median(v)) if v else None for v in lenslet],
        f"{name}_per_lenslet_nodes": [len(v) for v in lenslet],
    }


def predicted_nodes_nmse(
    predictions: np.ndarray,
    targets: np.ndarray,
    eps: np.ndarray,
    held: np.ndarray,
    oversample: int,
    basis: np.ndarray | list[np.ndarray] | None = None,
    terms: tuple[int, ...] = (),
) -> dict[str, Any]:
    """Held-out NMSE, as :func:`leave_one_out_pixels` measures it, of node PSFs predicted by a
    model fitted without them: ``predictions`` (H, J, h·S, w·S) of the nodes ``held`` (H,),
    registered as the crops, against ``targets``/``eps`` (N, …) as there; with ``basis`` (K, J,
    h·S, w·S, orthonormal; or per-lenslet bases ``[(K_j, h·S, w·S)]``, :func:`projector`) also
    projected on it first (``rank``), and on its first k terms (per lenslet) for each k of
    ``terms`` (``rank_vs_terms``). Per node, the mean and median, and per lenslet."""
    full = [_frame_errors(p, targets[n], eps[n], oversample) for p, n in zip(predictions, held, strict=True)]
    out: dict[str, Any] = _summary(full, "full") | {"n_heldout": len(full)}
    if basis is not None:
        project = projector(basis)
        rank = [
            _frame_errors(project(p), targets[n], eps[n], oversample) for p, n in zip(predictions, held, strict=True)
        ]
        out |= _summary(rank, "rank")
        if isinstance(basis, np.ndarray):
            out["K"] = int(len(basis))
        else:
            out["K"] = int(sum(len(b) for b in basis))
            out["K_per_lenslet"] = [int(len(b)) for b in basis]
        vs: dict[str, float] = {}
        for k in terms:
            truncated = projector(basis, k)
            errors = [
                _frame_nmse(truncated(p), targets[n], eps[n], oversample)
                for p, n in zip(predictions, held, strict=True)
            ]
            vs[str(k)] = float(np.mean(errors))
        if vs:
            out["rank_vs_terms"] = vs
    return out


class _Stacks:
    """The kept node PSFs by grid index: a node's own crop, or its axial stack at other depths."""

    def __init__(self, crops: np.ndarray, row_of: dict, keep: np.ndarray, z_mm: np.ndarray) -> None:
        self.crops, self.row_of, self.keep, self.zs = crops, row_of, keep, z_mm

    def at(self, index: np.ndarray, z_mm: np.ndarray | None) -> np.ndarray | None:
        """(J, h·S, w·S) float64 PSFs of node ``index`` (ix, iy, iz), or with ``z_mm`` (J,) those of
        its lateral position at those depths per lenslet (its axial stack interpolated linearly);
        None where a node needed is missing or held out."""
        if z_mm is None:
            row = self.row_of.get(tuple(index))
            return None if row is None or not self.keep[row] else self.crops[row].astype(np.float64)
        lo, hi, t = tent_pairs(axis_coordinate(z_mm, self.zs), len(self.zs))
        out = np.zeros(self.crops.shape[1:])
        for j in range(len(out)):
            for iz, weight in ((lo[j], 1 - t[j]), (hi[j], t[j])):
                row = self.row_of.get((int(index[0]), int(index[1]), int(iz)))
                if weight == 0:
                    continue
                if row is None or not self.keep[row]:
                    return None
                out[j] += weight * self.crops[row, j]
        return out


def _neighbour_predictions(
    stacks: _Stacks,
    node: np.ndarray,
    axes: tuple[np.ndarray, ...],
    surface: FocalSurface | None,
    turn: AzimuthTurn | None = None,
    which: str = "xyz",
    warp: bool = False,
) -> dict[str, np.ndarray]:
    """Node ``node`` (ix, iy, iz) predicted by linear interpolation between its two neighbours
    along x, y and z (those that exist and are kept); with ``surface`` the lateral neighbours'
    PSFs are taken at the node's defocus from their own best focus; with ``turn`` they are turned
    to the node's azimuth about each lenslet's axis first (:mod:`cm2optics.lsv.rotation`); with
    ``warp`` the two are blended by displacement interpolation (:mod:`cm2optics.lsv.warp`);
    ``which``: the axes to predict along."""
    x_n, y_n, z_n = (axes[k][node[k]] for k in range(3))
    predictions = {}
    for axis, name in enumerate("xyz"):
        if name not in which:
            continue
        lower, upper = node.copy(), node.copy()
        lower[axis] -= 1
        upper[axis] += 1
        if lower[axis] < 0 or upper[axis] >= len(axes[axis]):
            continue
        ends = []
        for index in (lower, upper):
            depth = None
            if surface is not None and axis < 2:  # the same defocus from the local best focus
                depth = z_n - surface.z_best(x_n, y_n) + surface.z_best(axes[0][index[0]], axes[1][index[1]])
            end = stacks.at(index, depth)
            if turn is not None and axis < 2 and end is not None:
                end = turn(end, (x_n, y_n), (axes[0][index[0]], axes[1][index[1]]), z_n, int(node[2]))
            ends.append(end)
        if ends[0] is None or ends[1] is None:
            continue
        xa, xb, xn = axes[axis][lower[axis]], axes[axis][upper[axis]], axes[axis][node[axis]]
        t = (xn - xa) / (xb - xa)
        if warp:
            pair = torch.as_tensor(np.stack(ends, axis=1), dtype=torch.float64)  # (J, 2, h, w)
            weights = np.broadcast_to([1 - t, t], (len(pair), 2))
            predictions[name] = displacement_blend(pair, weights).numpy()
        else:
            predictions[name] = (1 - t) * ends[0] + t * ends[1]
    return predictions


def leave_one_out_pixels(
    crops: np.ndarray,
    grid_index: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    targets: np.ndarray,
    eps: np.ndarray,
    oversample: int,
    *,
    rank: int = 64,
    held: np.ndarray,
    basis: np.ndarray | list[np.ndarray] | None = None,
    surface: FocalSurface | None = None,
    turn: AzimuthTurn | None = None,
    warp: bool = False,
) -> dict[str, Any]:
    """Held-out NMSE (module docstring) of the node PSFs ``crops`` (N, J, h·S, w·S) registered on
    the chief rays, against ``targets`` (N, J, h+3, w+3): each node's frame whose pixel (1 +
    h//2, 1 + w//2) holds the chief ray's integer part, ``eps`` (N, J, 2) its fraction.
    ``held``: the held-out nodes. ``basis``: a rank-K basis (K, J, h·S, w·S) to project on, or
    per-lenslet bases ``[(K_j, h·S, w·S)]`` (:func:`projector`; default: the SVD of the nodes not
    held out). ``surface``: each lenslet's best-focus surface;
    with it a lateral neighbour's PSF is taken at the same defocus from the local best focus
    (``z − z_best(x_n, y_n) + z_best(x_a, y_a)``, its axial stack interpolated linearly), as
    :func:`cm2optics.lsv.interpolate.defocus_nodes` does. ``turn``: each lateral neighbour's PSFs
    turned to the node's azimuth about each lenslet's axis before the blend
    (:class:`~cm2optics.lsv.rotation.AzimuthTurn`). ``warp``: neighbours blended by displacement
    interpolation (:mod:`cm2optics.lsv.warp`)."""
    S = int(oversample)
    N, J = crops.shape[:2]
    keep = np.ones(N, bool)
    keep[held] = False
    if basis is None:
        basis = decompose(crops[keep], rank).basis
    project = projector(basis)

    row_of = {tuple(k): n for n, k in enumerate(np.asarray(grid_index))}
    out: dict[str, list[float]] = {
        k: [] for k in ("at_node_full", "at_node_rank", "interpolated_full", "interpolated_rank")
    }
    per_axis: dict[str, list[float]] = {"x": [], "y": [], "z": []}

    def nmse(prediction: np.ndarray, n: int) -> float:
        return _frame_nmse(prediction, targets[n], eps[n], S)

    stacks = _Stacks(crops, row_of, keep, np.asarray(axes[2], float))
    for n in held:
        predictions = _neighbour_predictions(stacks, np.asarray(grid_index[n]), axes, surface, turn, warp=warp)
        if not predictions:
            continue
        full = np.mean(list(predictions.values()), axis=0)
        out["interpolated_full"].append(nmse(full, n))
        out["interpolated_rank"].append(nmse(project(full), n))
        out["at_node_full"].append(nmse(crops[n], n))
        out["at_node_rank"].append(nmse(project(crops[n]), n))
        for name, prediction in predictions.items():
            per_axis[name].append(nmse(project(prediction), n))
    result = {k: float(np.mean(v)) if v else None for k, v in out.items()}
    result["interpolated_rank_median"] = (
        float(np.median(out["interpolated_rank"])) if out["interpolated_rank"] else None
    )
    result["per_axis_rank"] = {k: float(np.mean(v)) if v else None for k, v in per_axis.items()}
    result["n_heldout"] = int(len(out["interpolated_rank"]))
    result["oversample"] = S
    result["rank"] = int(len(basis)) if isinstance(basis, np.ndarray) else int(sum(len(b) for b in basis))
    if result["at_node_full"] is not None:
        result["parts"] = {
            "sub_pixel_phase": result["at_node_full"],
            "shape_change_between_nodes": result["interpolated_full"] - result["at_node_full"],
            "low_rank": result["interpolated_rank"] - result["interpolated_full"],
        }
    return result


def turn_check(
    crops: np.ndarray,
    grid_index: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    surface: FocalSurface | None,
    turn: AzimuthTurn | None,
    *,
    warp: bool = False,
    n_heldout: int = 24,
    seed: int = 0,
    lateral: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Does turning the lateral neighbours' PSFs with the azimuth (and, with ``warp``, blending
    them by displacement interpolation) predict nodes left out better? For ``n_heldout`` seeded
    interior nodes, each node's registered crops (N, J, h, w) predicted from its x and y
    neighbours (the node left out, full rank, along ``surface`` if given) at a fixed orientation,
    turned (with ``turn``), warped and turned and warped (with ``warp``); returns the mean NMSE of
    each against the node's own crops (``nmse_<variant>``). ``lateral``: the indices of the x and
    y axis values to check on (default all; a scan with sub-pixel dithers passes one value per
    node, :func:`undithered_axis`, or a node's neighbour would be its own dither)."""
    gi = np.asarray(grid_index)
    if lateral is not None:  # the sub-grid: its own grid indices, the crops' rows kept
        position = [np.full(len(axes[k]), -1) for k in range(2)]
        for k in range(2):
            position[k][lateral[k]] = np.arange(len(lateral[k]))
        rows = np.flatnonzero((position[0][gi[:, 0]] >= 0) & (position[1][gi[:, 1]] >= 0))
        gi = np.stack([position[0][gi[rows, 0]], position[1][gi[rows, 1]], gi[rows, 2]], axis=1)
        axes = (np.asarray(axes[0])[lateral[0]], np.asarray(axes[1])[lateral[1]], axes[2])
    else:
        rows = np.arange(len(gi))
    held = heldout_nodes(gi, n_heldout, seed)  # positions in gi (and rows)
    keep = np.ones(len(crops), bool)
    stacks = _Stacks(crops, {tuple(k): n for k, n in zip(gi, rows, strict=True)}, keep, np.asarray(axes[2], float))
    variants = {"fixed_orientation": (None, False)}
    if turn is not None:
        variants["turned"] = (turn, False)
    if warp:
        variants["warped"] = (None, True)
        if turn is not None:
            variants["turned_warped"] = (turn, True)
    errors: dict[str, list[float]] = {name: [] for name in variants}
    for position in held:
        n = rows[position]
        keep[:] = True
        keep[n] = False  # this node alone left out
        y = np.asarray(crops[n], np.float64)
        norm = max(float((y**2).sum()), 1e-300)
        for name, (how, warping) in variants.items():
            predicted = _neighbour_predictions(stacks, gi[position], axes, surface, how, "xy", warping)
            if predicted:
                errors[name].append(float(np.mean([((p - y) ** 2).sum() / norm for p in predicted.values()])))
    return {
        "n_heldout": len(errors["fixed_orientation"]),
        **{f"nmse_{name}": (float(np.mean(v)) if v else None) for name, v in errors.items()},
    }
