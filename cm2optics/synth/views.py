"""The nine views cropped at the chief rays, and training patches cut from them.

View j is the ``view_px × view_px`` window of the measurement (or of lenslet j's crosstalk-free
image) whose pixel ``(view_px//2, view_px//2)`` is lenslet j's chief ray for the centre of the
focal plane (rounded to a pixel); outside the sensor it is zero (the authors' code zero-pads
the frame the same way). Stacked, the views of a source at the focal plane coincide: a patch at
the same place in the nine views sees the same object region.

A patch is a ``patch_px`` square at the same top-left in every view, drawn uniformly over the
views. Its volume target is the block of voxels imaged onto it at the focal plane, turned into
the views' orientation (the image through a lenslet is inverted, so the block is flipped),
``round(patch_px / |pixels per voxel|)`` voxels on a side, zero beyond the grid.
"""

from __future__ import annotations

import numpy as np

__all__ = ["crop_views", "patch_origins", "volume_patch"]


def crop_views(images: np.ndarray, chief_rays_px: np.ndarray, view_px: int) -> np.ndarray:
    """(J, view_px, view_px) windows of ``images`` ((H, W): the same image for every view, or
    (J, H, W): image j for view j) centred on the chief rays (J, 2)."""
    images = np.asarray(images)
    rays = np.asarray(chief_rays_px, float).reshape(-1, 2)
    J = len(rays)
    if images.ndim == 2:
        images = np.broadcast_to(images, (J,) + images.shape)
    if images.ndim != 3 or images.shape[0] != J:
        raise ValueError(f"images must be (H, W) or ({J}, H, W), got shape {images.shape}")
    H, W = images.shape[1:]
    out = np.zeros((J, view_px, view_px), dtype=np.float32)
    for j in range(J):
        r0 = int(np.round(rays[j, 0])) - view_px // 2
        c0 = int(np.round(rays[j, 1])) - view_px // 2
        rs, re = max(r0, 0), min(r0 + view_px, H)
        cs, ce = max(c0, 0), min(c0 + view_px, W)
        if rs < re and cs < ce:
            out[j, rs - r0 : re - r0, cs - c0 : ce - c0] = images[j, rs:re, cs:ce]
    return out


def patch_origins(rng: np.random.Generator, view_px: int, patch_px: int, count: int) -> np.ndarray:
    """(count, 2) top-left (row, col) of patches drawn uniformly within the views."""
    if patch_px > view_px:
        raise ValueError(f"patch_px = {patch_px} exceeds view_px = {view_px}")
    return rng.integers(0, view_px - patch_px + 1, size=(count, 2))


def volume_patch(
    volume: np.ndarray, origin: np.ndarray, view_px: int, patch_px: int, pixels_per_voxel: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The voxels imaged onto the view patch at ``origin`` (see the module docstring): the block
    (nz, q, q) in the views' orientation and the voxel (iy, ix) of its first row/column before
    the flip."""
    nz, ny, nx = volume.shape
    scale = np.asarray(pixels_per_voxel, float)
    q = int(max(round(patch_px / abs(scale[0])), 1)), int(max(round(patch_px / abs(scale[1])), 1))
    out = np.zeros((nz, q[0], q[1]), dtype=np.float32)
    starts = []
    for axis, (n, s, size) in enumerate(zip((ny, nx), scale, q, strict=True)):
        centre_px = origin[axis] + (patch_px - 1) / 2.0 - view_px // 2  # from the chief ray
        centre_voxel = (n - 1) / 2.0 + centre_px / s
        starts.append(int(np.round(centre_voxel - (size - 1) / 2.0)))
    iy0, ix0 = starts
    rs, re = max(iy0, 0), min(iy0 + q[0], ny)
    cs, ce = max(ix0, 0), min(ix0 + q[1], nx)
    if rs < re and cs < ce:
        out[:, rs - iy0 : re - iy0, cs - ix0 : ce - ix0] = volume[:, rs:re, cs:ce]
    if scale[0] < 0:
        out = out[:, ::-1, :]
    if scale[1] < 0:
        out = out[:, :, ::-1]
    return np.ascontiguousarray(out), np.array([iy0, ix0])
