"""Registering the nine views onto the model's affine geometry over the whole field.

The views are cropped at the lenslets' chief rays, and the refocusing shifts them by whole pixels
the same everywhere (:mod:`~cm2optics.recon.net.refocus`): both assume that a source at (x, y)
of the focal plane lands in every view at the same place, ``A(0)·(x, y)`` px from the view's
centre (:class:`~cm2optics.lsv.preprocess.Geometry`). Each lenslet sees the field at its own
angle, so its distortion differs from its neighbours': in the whole-sensor model of cm2-v2
the foci of one source miss that place by up to ≈ 25 px at 3.5 mm off axis (≈ 3 px at 0.9 mm),
and the nine views no longer agree — a shift-and-add then adds unrelated light, and a
convolutional network, which cannot tell where in the field a patch lies, cannot undo it.

The fix is a resampling: view j is read at ``p + δ_j(x, y)``, where ``δ_j`` is the
displacement of lenslet j's focus from the affine place for the source at ``(x, y) = A(0)⁻¹·p``
on the focal plane, taken from the model's own PSFs (the thresholded centroid of each lenslet's
focus patch, :meth:`~cm2optics.lsv.model.LSVModel.focus_patches`) on a lateral grid and
interpolated bilinearly between its nodes (plus the fraction of a pixel by which the crop
missed the chief ray). Where a lenslet is dark (vignetted) its displacement
is that of the nearest place it is lit. After registration the same source lands at the same
view pixel in every view, so the integer refocusing shifts and the volume's lateral mapping hold
over the whole field.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["focus_displacements", "register_views", "registration_map"]

#: Fraction of a patch's peak below which its pixels do not count in the focus centroid.
CENTROID_THRESHOLD = 0.3
#: A lenslet counts as lit at a place if its focus patch holds this fraction of the brightest one.
LIT_FRACTION = 0.02


def focus_displacements(model, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: float = 0.0, chunk: int = 256):
    """((n, J, 2) displacement (row, col) px of each lenslet's focus centroid from the geometry's
    focus, (n, J) light in each focus patch) for sources at (x_mm, y_mm, z_mm), flattened."""
    x = np.asarray(x_mm, float).ravel()
    y = np.asarray(y_mm, float).ravel()
    K, J, h, w = model.basis.shape
    S = int(getattr(model, "oversample", 1))
    rows = (np.arange(h) - (h // 2)) / S
    cols = (np.arange(w) - (w // 2)) / S
    shift = np.zeros((len(x), J, 2))
    light = np.zeros((len(x), J))
    for j in range(J):
        # a per-lenslet basis: only lenslet j's own terms have light in it (all K otherwise)
        terms = model.lenslet_terms(j) if hasattr(model, "lenslet_terms") else np.arange(K)
        basis = model.basis[terms, j].reshape(len(terms), -1).astype(np.float32)
        for start in range(0, len(x), chunk):
            sl = slice(start, start + chunk)
            c = model.coefficients_at(x[sl], y[sl], np.full(len(x[sl]), z_mm), lenslet=j).astype(np.float32)
            patches = (c[:, terms] @ basis).reshape(-1, h, w)
            peak = patches.max(axis=(1, 2), keepdims=True)
            weight = np.clip(patches - CENTROID_THRESHOLD * peak, 0.0, None)
            total = weight.sum(axis=(1, 2))
            safe = np.maximum(total, 1e-30)
            shift[sl, j, 0] = np.einsum("nhw,h->n", weight, rows) / safe
            shift[sl, j, 1] = np.einsum("nhw,w->n", weight, cols) / safe
            light[sl, j] = np.clip(patches, 0.0, None).sum(axis=(1, 2))
    return shift, light


def _filled(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``values`` (ny, nx, …) with every invalid node given its nearest valid node's value."""
    if valid.all() or not valid.any():
        return values if valid.any() else np.zeros_like(values)
    _, (iy, ix) = ndimage.distance_transform_edt(~valid, return_indices=True)
    return values[iy, ix]


def registration_map(model, view_px: int, step_mm: float = 0.125, z_mm: float = 0.0) -> np.ndarray:
    """(J, 2, V, V) float32 sensor-relative sampling positions (row, col) for each view's pixels:
    view j's registered pixel p is its pixel ``p + δ_j`` (see the module docstring); V = view_px."""
    if not all(hasattr(model, name) for name in ("basis", "coefficients_at", "geometry")):
        raise ValueError(f"{type(model).__name__}: registering the views needs a 3D-LSV model (its focus patches)")
    g = model.geometry
    A_inv = np.linalg.inv(g.A(z_mm))
    V = int(view_px)
    centre = V // 2
    corners = np.array([[-centre, -centre], [-centre, V - centre], [V - centre, -centre], [V - centre, V - centre]])
    reach = np.abs(corners @ A_inv.T).max() + step_mm
    axis = np.arange(-reach, reach + step_mm / 2, step_mm)
    xx, yy = np.meshgrid(axis, axis)  # node (iy, ix) ↔ (x = axis[ix], y = axis[iy])
    shift, light = focus_displacements(model, xx, yy, z_mm)
    n = len(axis)
    shift = shift.reshape(n, n, -1, 2)
    lit = light.reshape(n, n, -1) >= LIT_FRACTION * light.max()
    J = shift.shape[2]
    p = np.arange(V, dtype=float) - centre
    pr, pc = np.meshgrid(p, p, indexing="ij")
    xy = np.einsum("ab,bhw->ahw", A_inv, np.stack([pr, pc]))  # (x, y) mm of each view pixel
    at = np.stack([(xy[1] - axis[0]) / step_mm, (xy[0] - axis[0]) / step_mm])  # fractional (iy, ix)
    # crop_views centres view j on its chief ray rounded to a pixel: the fraction left over
    chief = np.asarray(g.focus(0.0, 0.0, 0.0), float).reshape(-1, 2)
    fraction = chief - np.round(chief)
    out = np.empty((J, 2, V, V), np.float32)
    for j in range(J):
        field = _filled(shift[:, :, j], lit[:, :, j])
        for axis_index in range(2):
            delta = ndimage.map_coordinates(field[..., axis_index], at, order=1, mode="nearest")
            out[j, axis_index] = (pr if axis_index == 0 else pc) + centre + fraction[j, axis_index] + delta
    return out


def register_views(views: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """(J, V, V) views resampled bilinearly at ``positions`` (:func:`registration_map`; zeros
    beyond the views), float32."""
    views = np.asarray(views, np.float32)
    if views.shape[0] != positions.shape[0] or views.shape[1:] != positions.shape[2:]:
        raise ValueError(f"views {views.shape} do not match the registration map {positions.shape}")
    return np.stack(
        [
            ndimage.map_coordinates(v, pos, order=1, mode="constant", cval=0.0)
            for v, pos in zip(views, positions, strict=True)
        ]
    ).astype(np.float32)
