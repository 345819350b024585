"""``cm2 lsv validate``: the model's error where it was not calibrated.

Two cases, chosen by comparing the scan with the one the model was built from:

- **The calibration scan itself: leave-one-out.** For each held-out node (interior nodes,
  a seeded sample), the SVD is redone without it and its coefficients are predicted from its
  neighbours along x, along y and along z (linear between the two neighbours, then averaged);
  the predicted focus array is compared with the measured crops (with the model's focal
  surface, a lateral neighbour's coefficients are its axial stack's at the same defocus from its
  own best focus, lenslet by lenslet). Everything runs on Gram
  matrices of the crops (per lenslet), so no pixel is touched twice.
  A model that turns its lateral neighbours with the azimuth (:mod:`cm2optics.lsv.rotation`)
  also gets ``leave_one_out_turned``: held-out nodes predicted from their x and y neighbours with
  and without the turn, full rank, on the crops (:func:`~cm2optics.lsv.epsf_validate.turn_check`);
  likewise a model that warps them (:mod:`cm2optics.lsv.warp`), with and without the warp.
- **Another scan (e.g. offset by half a step): held-out positions.** Each position's image from
  the model (:meth:`LSVModel.point_image`) is compared with the measured image over the model's
  focus windows.

Error = ``‖prediction − measurement‖² / ‖measurement‖²`` per position, averaged (``nmse_heldout``),
against K, and for models built on a sparser grid: every other lateral node dropped
(``lateral_2x``) or every other depth (``axial_2x``), predicted at the dropped nodes through the
model's own interpolation (along the chief rays). The paper found lateral sub-sampling to hurt
more than axial.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cm2optics.formats.scan import ScanIndex, open_scan
from cm2optics.lsv.build import scan_fingerprint
from cm2optics.lsv.epsf_validate import turn_check
from cm2optics.lsv.interpolate import axis_coordinate, chief_ray_nodes, defocus_nodes, tent_pairs
from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.preprocess import extract_crops, prepared_image
from cm2optics.lsv.rotation import AzimuthTurn

__all__ = ["image_errors", "validate_model"]

Progress = Callable[[str, int, int], None]
DEFAULT_RANKS = (1, 4, 8, 16, 32, 64, 128)


def _ranks(model: LSVModel, ranks: tuple[int, ...] | None, limit: int) -> list[int]:
    chosen = sorted({k for k in (ranks or DEFAULT_RANKS) if 1 <= k <= limit} | {min(model.rank, limit)})
    dropped = sorted(k for k in ranks or () if k > limit)
    if dropped:
        warnings.warn(
            f"--ranks: {', '.join(map(str, dropped))} exceed the {limit} basis PSFs this check can hold; "
            f"using ranks {', '.join(map(str, chosen))}",
            stacklevel=3,
        )
    return chosen


def _svd(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    values, vectors = (t.numpy() for t in torch.linalg.eigh(torch.as_tensor(G, dtype=torch.float64)))
    order = np.argsort(values)[::-1]
    values = np.clip(values[order], 0, None)
    return np.sqrt(values), vectors[:, order]


def _quadratic_error(Gj: list[np.ndarray], alphas: list[np.ndarray], n: int) -> float:
    """Σ_j ‖Σ_m α_jm x_mj − x_nj‖² / Σ_j ‖x_nj‖² through the per-lenslet Gram matrices."""
    error = 0.0
    norm = 0.0
    for G, a in zip(Gj, alphas, strict=True):
        error += float(a @ G @ a - 2 * a @ G[:, n] + G[n, n])
        norm += float(G[n, n])
    return max(error, 0.0) / norm if norm > 0 else float("nan")


def _interior(gi: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    ok = np.ones(len(gi), bool)
    for axis, n in enumerate(shape):
        if n >= 3:
            ok &= (gi[:, axis] > 0) & (gi[:, axis] < n - 1)
    return np.nonzero(ok)[0]


def _leave_one_out(
    model: LSVModel,
    crops: np.ndarray,
    gi: np.ndarray,
    ranks: list[int],
    n_heldout: int,
    seed: int,
    progress: Progress | None,
) -> dict[str, Any]:
    N, J = crops.shape[:2]
    X = crops.reshape(N, J, -1).astype(np.float64)
    Gj = [X[:, j] @ X[:, j].T for j in range(J)]
    G = sum(Gj)
    shape = (len(model.grid_x_mm), len(model.grid_y_mm), len(model.grid_z_mm))
    row_of = {tuple(k): n for n, k in enumerate(gi)}
    candidates = _interior(gi, shape)
    rng = np.random.default_rng(seed)
    if n_heldout > len(candidates):
        warnings.warn(
            f"--heldout {n_heldout}: the scan has only {len(candidates)} interior positions to hold out; "
            f"using {len(candidates)}",
            stacklevel=3,
        )
    held = (
        rng.choice(candidates, size=min(n_heldout, len(candidates)), replace=False)
        if len(candidates)
        else np.array([], int)
    )
    per_rank: dict[int, list[float]] = {k: [] for k in ranks}
    per_axis: dict[str, list[float]] = {"x": [], "y": [], "z": []}
    K_model = min(model.rank, N - 1)
    for count, n in enumerate(held):
        others = np.array([m for m in range(N) if m != n])
        s, V = _svd(G[np.ix_(others, others)])
        coefficients = V * s  # (N-1, N-1)
        local = {m: i for i, m in enumerate(others)}
        predictions = _neighbour_coefficients(model, gi[n], row_of, local, coefficients, J)
        if not predictions:
            continue
        mean = np.mean(list(predictions.values()), axis=0)  # (J, N-1)
        for K in ranks:
            k = min(K, len(s))
            inverse = np.where(s[:k] > s[0] * 1e-9, 1.0 / np.maximum(s[:k], 1e-300), 0.0)
            per_rank[K].append(_loo_error(Gj, others, mean[:, :k] * inverse @ V[:, :k].T, n))
        k = min(K_model, len(s))
        inverse = np.where(s[:k] > s[0] * 1e-9, 1.0 / np.maximum(s[:k], 1e-300), 0.0)
        for name, prediction in predictions.items():
            per_axis[name].append(_loo_error(Gj, others, prediction[:, :k] * inverse @ V[:, :k].T, n))
        if progress:
            progress("leave-one-out", count + 1, len(held))
    rank = min(model.rank, max(ranks))
    return {
        "method": "leave-one-out",
        "n_heldout": int(len(held)),
        "nmse_heldout": float(np.mean(per_rank[rank])) if per_rank[rank] else None,
        "nmse_heldout_per_axis": {k: (float(np.mean(v)) if v else None) for k, v in per_axis.items()},
        "nmse_heldout_vs_rank": {str(k): (float(np.mean(v)) if v else None) for k, v in per_rank.items()},
    }


def _neighbour_coefficients(
    model: LSVModel, node: np.ndarray, row_of: dict, local: dict[int, int], coefficients: np.ndarray, J: int
) -> dict[str, np.ndarray]:
    """Node ``node`` (ix, iy, iz)'s coefficients (J, N−1) per lenslet, predicted linearly between its
    two neighbours along x, y and z; with the model's focal surface a lateral neighbour's are
    those of its axial stack at the same defocus from its own best focus (per lenslet)."""
    axes_mm = (model.grid_x_mm, model.grid_y_mm, model.grid_z_mm)
    x_n, y_n, z_n = (axes_mm[k][node[k]] for k in range(3))
    surface = model.focal_surface
    z_best_n = None if surface is None else surface.z_best(x_n, y_n)  # (J,)
    predictions: dict[str, np.ndarray] = {}
    for axis, name in enumerate("xyz"):
        lower, upper = node.copy(), node.copy()
        lower[axis] -= 1
        upper[axis] += 1
        if lower[axis] < 0 or upper[axis] >= len(axes_mm[axis]):
            continue
        ends = []
        for index in (lower, upper):
            depths = None  # the neighbour's own node; laterally with a surface: the same defocus there
            if surface is not None and axis < 2:
                depths = z_n - z_best_n + surface.z_best(axes_mm[0][index[0]], axes_mm[1][index[1]])
            ends.append(_stack_coefficients(model, index, depths, row_of, local, coefficients, J))
        if ends[0] is None or ends[1] is None:
            continue
        xa, xb, xn = axes_mm[axis][lower[axis]], axes_mm[axis][upper[axis]], axes_mm[axis][node[axis]]
        t = (xn - xa) / (xb - xa)
        predictions[name] = (1 - t) * ends[0] + t * ends[1]
    return predictions


def _stack_coefficients(
    model: LSVModel,
    index: np.ndarray,
    depths_mm: np.ndarray | None,
    row_of: dict,
    local: dict[int, int],
    coefficients: np.ndarray,
    J: int,
) -> np.ndarray | None:
    """(J, N−1) coefficients of node ``index`` (ix, iy, iz), or with ``depths_mm`` (J,) those of
    its axial stack at those depths per lenslet (linear); None if a node needed is missing or held
    out."""
    if depths_mm is None:
        row = row_of.get(tuple(index))
        return None if row not in local else np.broadcast_to(coefficients[local[row]], (J, coefficients.shape[1]))
    zs = model.grid_z_mm
    lo, hi, t = tent_pairs(axis_coordinate(depths_mm, zs), len(zs))
    out = np.zeros((J, coefficients.shape[1]))
    for j in range(J):
        for iz, weight in ((lo[j], 1 - t[j]), (hi[j], t[j])):
            row = row_of.get((index[0], index[1], int(iz)))
            if weight == 0:
                continue
            if row not in local:
                return None
            out[j] += weight * coefficients[local[row]]
    return out


def _loo_error(Gj: list[np.ndarray], others: np.ndarray, alphas: np.ndarray, n: int) -> float:
    """Held-out error of lenslet-wise weights ``alphas`` (J, N−1) of the other nodes' crops."""
    full = np.zeros((len(Gj), Gj[0].shape[0]))
    full[:, others] = alphas
    return _quadratic_error(Gj, list(full), n)


def _subgrid(
    model: LSVModel, crops: np.ndarray, gi: np.ndarray, keep: np.ndarray, ranks: list[int]
) -> dict[str, float | None]:
    """Error at the dropped nodes of models built on the kept nodes only, per rank."""
    N, J = crops.shape[:2]
    X = crops.reshape(N, J, -1).astype(np.float64)
    kept = np.nonzero(keep)[0]
    dropped = np.nonzero(~keep)[0]
    if len(kept) < 2 or len(dropped) == 0:
        return {str(k): None for k in ranks}
    Xk = X[kept]  # (n_kept, J, D)
    Xd = X[dropped]
    G_kk = [Xk[:, j] @ Xk[:, j].T for j in range(J)]
    G_kd = [Xk[:, j] @ Xd[:, j].T for j in range(J)]
    norms = np.einsum("njd,njd->n", Xd, Xd)
    axes_full = (model.grid_x_mm, model.grid_y_mm, model.grid_z_mm)
    sub_axes = tuple(np.unique(axes_full[a][gi[kept, a]]) for a in range(3))
    sub_index = [np.searchsorted(sub_axes[a], axes_full[a][gi[kept, a]]) for a in range(3)]
    s, V = _svd(sum(G_kk))
    coefficients = V * s  # (n_kept, n_kept)
    grid = np.zeros((len(kept), len(sub_axes[2]), len(sub_axes[1]), len(sub_axes[0])))
    grid[:, sub_index[2], sub_index[1], sub_index[0]] = coefficients.T
    x, y, z = (axes_full[a][gi[dropped, a]] for a in range(3))
    interpolated = []
    for j in range(J):
        if model.focal_surface is not None:  # the model's own interpolation: along the focal surface
            nodes, weights = defocus_nodes(model.focal_surface, sub_axes, j, x, y, z)
        else:
            nodes, weights = chief_ray_nodes(model.geometry, sub_axes, j, x, y, z)  # (n_d, 8, 3), (n_d, 8)
        interpolated.append(np.einsum("knm,nm->nk", grid[:, nodes[..., 0], nodes[..., 1], nodes[..., 2]], weights))
    out: dict[str, float | None] = {}
    for K in ranks:
        k = min(K, len(s))
        inverse = np.where(s[:k] > s[0] * 1e-9, 1.0 / np.maximum(s[:k], 1e-300), 0.0)
        error = norms.copy()
        for j in range(J):
            alpha = V[:, :k] @ (inverse[:, None] * interpolated[j][:, :k].T)  # (n_kept, n_d)
            error += np.einsum("mn,mn->n", alpha, G_kk[j] @ alpha) - 2 * np.einsum("mn,mn->n", alpha, G_kd[j])
        valid = norms > 0
        out[str(K)] = float(np.mean(np.clip(error[valid], 0, None) / norms[valid])) if valid.any() else None
    return out


def _second_scan(
    model: LSVModel, index: ScanIndex, ranks: list[int], max_positions: int, seed: int, progress: Progress | None
) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    chosen = (
        np.arange(len(index))
        if len(index) <= max_positions
        else np.sort(rng.choice(len(index), max_positions, replace=False))
    )
    h, w = model.patch_shape
    per_rank: dict[int, list[float]] = {k: [] for k in ranks}
    ratios = []
    models = {K: model.truncated(K) for K in ranks}
    for count, n in enumerate(chosen):
        x, y, z = index.positions_mm[n]
        measured = prepared_image(index, n).astype(np.float64) * model.scale
        mask = np.zeros(model.sensor_shape, bool)
        for r, c in model.geometry.focus(x, y, z):
            r0, c0 = int(round(r)) - h // 2, int(round(c)) - w // 2
            mask[max(r0, 0) : max(r0 + h, 0), max(c0, 0) : max(c0 + w, 0)] = True
        target = measured[mask]
        norm = float(target @ target)
        if norm <= 0:
            continue
        for K, m in models.items():
            predicted = m.point_image(x, y, z)[mask]
            per_rank[K].append(float(((predicted - target) ** 2).sum() / norm))
            if K == max(models):
                ratios.append(float(predicted @ target / max(predicted @ predicted, 1e-300)))
        if progress:
            progress("held-out positions", count + 1, len(chosen))
    rank = min(model.rank, max(ranks))
    return {
        "method": "second scan",
        "n_heldout": int(len(per_rank[rank])),
        "nmse_heldout": float(np.mean(per_rank[rank])) if per_rank[rank] else None,
        "nmse_heldout_vs_rank": {str(k): (float(np.mean(v)) if v else None) for k, v in per_rank.items()},
        "brightness_ratio": float(np.median(ratios)) if ratios else None,
    }


def validate_model(
    model: LSVModel,
    scan_dir: str | Path,
    *,
    ranks: tuple[int, ...] | None = None,
    n_heldout: int = 48,
    max_positions: int = 200,
    subsample: bool = True,
    seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Held-out error of ``model`` on ``scan_dir`` (see the module docstring); a JSON-able dict
    with at least ``nmse_heldout``."""
    index = open_scan(scan_dir)
    if index.shape != model.sensor_shape:
        raise ValueError(f"{scan_dir}: images are {index.shape}, the model's sensor is {model.sensor_shape}")
    calibration = model.provenance.get("scan", {})
    same = calibration.get("fingerprint") == scan_fingerprint(index)
    result: dict[str, Any] = {"rank": model.rank, "scan": str(Path(scan_dir).resolve())}
    crops = gi = None
    if same:
        crops = extract_crops(index, model.geometry, model.patch_shape, progress=progress) * np.float32(model.scale)
        gi = index.grid_index()
        if model.n_lenslets > 1 and all(len(model.lenslet_terms(j)) < model.rank for j in range(model.n_lenslets)):
            message = (
                "the model has a per-lenslet basis, but this check decomposes one basis of focus arrays (K terms in "
                "all, not per lenslet): its held-out figures are not this model's (epsf_validate.predicted_nodes_nmse "
                "takes the model's own basis)"
            )
            warnings.warn(message, stacklevel=2)
            result["basis_warning"] = message
        result.update(_leave_one_out(model, crops, gi, _ranks(model, ranks, len(index) - 1), n_heldout, seed, progress))
        if model.rotate_aberrations or model.warp_shapes:  # the Gram-matrix check cannot turn or warp PSFs
            turn = None
            if model.rotate_aberrations:
                turn = AzimuthTurn.of_model(model)
                turn = replace(turn, pivots=turn.pivots / model.oversample)  # whole-pixel crops
            result["leave_one_out_turned"] = turn_check(
                crops, gi, model.axes, model.focal_surface, turn, warp=model.warp_shapes, n_heldout=n_heldout, seed=seed
            )
        if model.oversample > 1:
            result["note"] = (
                "leave-one-out of the scan's whole-pixel registered crops: the model's ePSF basis is not used "
                "here (cm2optics.lsv.epsf_validate.leave_one_out_pixels checks it in pixels)"
            )
    else:
        result.update(_second_scan(model, index, _ranks(model, ranks, model.rank), max_positions, seed, progress))
        folder = calibration.get("folder")
        if subsample and folder and Path(folder).is_dir():
            calibration_index = open_scan(folder)
            if scan_fingerprint(calibration_index) == calibration.get("fingerprint"):
                crops = extract_crops(
                    calibration_index, model.geometry, model.patch_shape, progress=progress
                ) * np.float32(model.scale)
                gi = calibration_index.grid_index()
    if subsample and crops is not None:
        ranks_sub = _ranks(model, ranks, len(crops) // 2)
        lateral = (gi[:, 0] % 2 == 0) & (gi[:, 1] % 2 == 0)
        axial = gi[:, 2] % 2 == 0
        rank = str(min(model.rank, max(ranks_sub)))
        lateral_errors = _subgrid(model, crops, gi, lateral, ranks_sub)
        axial_errors = _subgrid(model, crops, gi, axial, ranks_sub)
        result["nmse_subsampled"] = {"lateral_2x": lateral_errors.get(rank), "axial_2x": axial_errors.get(rank)}
        result["nmse_subsampled_vs_rank"] = {"lateral_2x": lateral_errors, "axial_2x": axial_errors}
    return result


def image_errors(model_image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """How well ``model_image`` reproduces ``reference`` (two images of the same shape, in the
    same units: e.g. a traced image divided by the total of the traced in-focus on-axis source,
    which is the model's unit).

    error: ‖m − r‖ / ‖r‖. shape_error: min over s of ‖s·m − r‖ / ‖r‖ (the error left once
    the total is fitted). flux_ratio: Σm / Σr.
    """
    m = np.asarray(model_image, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if m.shape != r.shape:
        raise ValueError(f"model image {m.shape} and reference {r.shape} differ in shape")
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(r))):
        raise ValueError("images contain NaN or infinite values")
    norm = float(np.linalg.norm(r))
    if not norm > 0:
        raise ValueError("the reference image is empty")
    mm = float(np.sum(m * m))
    scale = float(np.sum(m * r)) / mm if mm > 0 else 0.0
    return {
        "error": float(np.linalg.norm(m - r)) / norm,
        "shape_error": float(np.linalg.norm(scale * m - r)) / norm,
        "flux_ratio": float(m.sum() / r.sum()) if r.sum() != 0 else float("nan"),
    }
