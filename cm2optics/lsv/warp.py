"""Shape-preserving (displacement) interpolation between neighbouring node PSFs.

Blending two foci of different size or elongation linearly gives a ghosted double shape, not the
shape in between. Displacement interpolation moves mass instead: for Gaussian-like foci the
optimal-transport (McCann) interpolation between two shapes is the affine map that matches their
second moments. Here every neighbour's focus is described by its centroid ``c_l`` and 2 × 2
covariance ``Σ_l`` (:func:`focus_moments`, weighted by the squared PSF so that faint wings and
low-rank ripples do not count); the target shape is the weighted log-Euclidean mean of the
neighbours' covariances (``exp Σ w_l log Σ_l``: equal to each at its own node, geometric in
between, so an astigmatic focus that turns from vertical to horizontal passes through round and
a defocus blur grows smoothly), at the weighted mean centroid; each neighbour is warped onto it
by the symmetric transport map ``T_l`` (``T_l Σ_l T_l = Σ_t``, :func:`transport_maps`) about its
centroid, flux conserved (÷ det T_l), and the warped PSFs are blended with the same weights. A
turn with the azimuth (:mod:`cm2optics.lsv.rotation`) is composed into the same resampling.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "MAX_STRETCH",
    "affine_resample",
    "displacement_blend",
    "focus_moments",
    "log_euclidean_mean",
    "transport_maps",
]

#: A transport map's stretch along either principal axis is clipped to [1/MAX_STRETCH,
#: MAX_STRETCH] (a vignetted or nearly empty focus must not be blown up).
MAX_STRETCH = 3.0


def affine_resample(
    patches: torch.Tensor, matrices: np.ndarray, out_centres: np.ndarray, in_centres: np.ndarray
) -> torch.Tensor:
    """(M, h, w) patches resampled so that output sample x (row, col) takes the input's value at
    ``in_centres + matrices · (x − out_centres)`` (matrices (M, 2, 2), centres (M, 2) or (2,), in
    samples); bicubic, zero outside (no flux scaling)."""
    M, h, w = patches.shape
    m = np.broadcast_to(np.asarray(matrices, float), (M, 2, 2))
    co = np.broadcast_to(np.asarray(out_centres, float), (M, 2))
    ci = np.broadcast_to(np.asarray(in_centres, float), (M, 2))
    # grid_sample's coordinates (x: col, y: row, each −1…1 across the samples) of the source of
    # output sample (r, c): origin + r·per_row + c·per_col, summed from its row and column parts
    scale = np.array([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)])  # (x, y) per sample
    origin = (ci - np.einsum("mij,mj->mi", m, co))[:, ::-1] * scale - 1.0  # (M, 2) as (x, y)
    per_row, per_col = m[:, ::-1, 0] * scale, m[:, ::-1, 1] * scale
    options = {"dtype": patches.dtype, "device": patches.device}
    r = torch.arange(h, **options)[None, :, None]
    c = torch.arange(w, **options)[None, :, None]
    by_row = torch.as_tensor(origin, **options)[:, None] + r * torch.as_tensor(per_row, **options)[:, None]
    by_col = c * torch.as_tensor(per_col, **options)[:, None]
    grid = by_row[:, :, None] + by_col[:, None]  # (M, h, w, 2)
    out = torch.nn.functional.grid_sample(
        patches[:, None], grid, mode="bicubic", padding_mode="zeros", align_corners=True
    )
    return out[:, 0]


def focus_moments(patches: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid (M, 2) and covariance (M, 2, 2) (samples², (row, col)) of each patch's focus,
    weighted by the squared positive part of the PSF (for a Gaussian focus: its centre and half
    its covariance); and each patch's weight total (M,) (0: an empty patch). Sums over the
    patch's row and column profiles (coordinates from the patch centre, float64 sums)."""
    M, h, w = patches.shape
    q = torch.clamp(patches.float(), min=0.0) ** 2
    rows = torch.arange(h, dtype=q.dtype) - (h - 1) / 2
    cols = torch.arange(w, dtype=q.dtype) - (w - 1) / 2
    by_row = q.sum(dim=2).double()  # (M, h)
    by_col = q.sum(dim=1).double()  # (M, w)
    cross = (q @ cols).double() @ rows.double()  # (M,): Σ q·r·c
    r, c = rows.double(), cols.double()
    total = by_row.sum(dim=1)
    safe = torch.where(total > 0, total, torch.ones_like(total))
    mr, mc = by_row @ r / safe, by_col @ c / safe
    crr = by_row @ (r * r) / safe - mr * mr
    ccc = by_col @ (c * c) / safe - mc * mc
    crc = cross / safe - mr * mc
    covariance = torch.stack([torch.stack([crr, crc], -1), torch.stack([crc, ccc], -1)], -2)
    centre = torch.tensor([(h - 1) / 2, (w - 1) / 2], dtype=torch.float64)
    return (torch.stack([mr, mc], -1) + centre).numpy(), covariance.numpy(), total.numpy()


def _symmetric_function(matrices: np.ndarray, function) -> np.ndarray:
    """``function`` applied to the eigenvalues of symmetric matrices (…, 2, 2)."""
    values, vectors = np.linalg.eigh(matrices)
    return np.einsum("...ij,...j,...kj->...ik", vectors, function(values), vectors)


def log_euclidean_mean(covariances: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """``exp(Σ_l w_l log Σ_l) `` of SPD matrices (M, L, 2, 2) with weights (M, L) summing to 1."""
    logs = _symmetric_function(covariances, lambda v: np.log(np.maximum(v, 1e-12)))
    return _symmetric_function(np.einsum("mlij,ml->mij", logs, weights), np.exp)


def transport_maps(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Symmetric positive maps T (…, 2, 2) with ``T Σ_s T = Σ_t`` (the optimal-transport map
    between centred Gaussians): ``Σ_s^{-1/2} (Σ_s^{1/2} Σ_t Σ_s^{1/2})^{1/2} Σ_s^{-1/2}``; their
    principal stretches clipped to [1/:data:`MAX_STRETCH`, :data:`MAX_STRETCH`]."""
    root = _symmetric_function(source, lambda v: np.sqrt(np.maximum(v, 1e-12)))
    inverse_root = _symmetric_function(source, lambda v: 1.0 / np.sqrt(np.maximum(v, 1e-12)))
    middle = _symmetric_function(root @ target @ root, lambda v: np.sqrt(np.maximum(v, 0.0)))
    T = inverse_root @ middle @ inverse_root
    T = 0.5 * (T + np.swapaxes(T, -1, -2))
    return _symmetric_function(T, lambda v: np.clip(v, 1.0 / MAX_STRETCH, MAX_STRETCH))


def displacement_blend(psfs: torch.Tensor, weights: np.ndarray, turns: np.ndarray | None = None) -> torch.Tensor:
    """Blend (M, h, w) of neighbour PSFs ``psfs`` (M, L, h, w) with ``weights`` (M, L) (summing
    to 1) by displacement interpolation (module docstring). ``turns``: optional (M, L, 2, 3)
    rotation about a pivot applied to each neighbour first, as ``[R | pivot]`` with R the forward
    rotation (the turned PSF at x is the PSF at ``pivot + Rᵀ(x − pivot)``); composed into the one
    resampling. Neighbours with zero weight or an empty patch are left out of the target shape
    (and zero-weight ones are not resampled)."""
    M, L, h, w = psfs.shape
    flat = psfs.reshape(M * L, h, w)
    weights = np.asarray(weights, float)
    active = np.flatnonzero(weights.reshape(-1) > 0)  # a zero-weight neighbour is neither measured nor resampled
    if len(active) == 0:
        return torch.zeros((M, h, w), dtype=psfs.dtype, device=psfs.device)
    centroid, covariance, total = np.zeros((M * L, 2)), np.tile(np.eye(2), (M * L, 1, 1)), np.zeros(M * L)
    centroid[active], covariance[active], total[active] = focus_moments(flat[active])
    centroid, covariance = centroid.reshape(M, L, 2), covariance.reshape(M, L, 2, 2)
    used = (weights > 0) & (total.reshape(M, L) > 0) & (np.linalg.det(covariance) > 0)
    shape_weights = np.where(used, weights, 0.0)
    shape_weights /= np.maximum(shape_weights.sum(axis=1, keepdims=True), 1e-300)
    rotation = np.broadcast_to(np.eye(2), (M, L, 2, 2))
    turned_centroid = centroid
    if turns is not None:
        rotation, pivot = turns[..., :2], turns[..., 2]
        turned_centroid = pivot + np.einsum("mlij,mlj->mli", rotation, centroid - pivot)
        covariance = rotation @ covariance @ np.swapaxes(rotation, -1, -2)
    safe = np.where(used[..., None, None], covariance, np.eye(2))
    target = log_euclidean_mean(safe, shape_weights)  # (M, 2, 2)
    target_centroid = np.einsum("mli,ml->mi", turned_centroid, shape_weights)
    T = transport_maps(safe, np.broadcast_to(target[:, None], safe.shape))
    T = np.where(used[..., None, None], T, np.eye(2))
    # output x ← turned PSF at c'_l + T⁻¹(x − c_t) ← node PSF at c_l + Rᵀ T⁻¹ (x − c_t)
    matrices = np.swapaxes(rotation, -1, -2) @ np.linalg.inv(T)
    out_centres = np.where(used[..., None], target_centroid[:, None], turned_centroid)
    warped = affine_resample(
        flat[active],
        matrices.reshape(-1, 2, 2)[active],
        out_centres.reshape(-1, 2)[active],
        centroid.reshape(-1, 2)[active],
    )
    gain = torch.as_tensor((weights / np.linalg.det(T)).reshape(-1)[active], dtype=psfs.dtype)
    out = torch.zeros((M, h * w), dtype=psfs.dtype, device=psfs.device)
    out.index_add_(0, torch.as_tensor(active // L), warped.reshape(len(active), -1) * gain[:, None])
    return out.reshape(M, h, w)
