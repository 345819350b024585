"""Interpolating the coefficients of the calibration grid in x, y and z.

Between grid nodes the coefficients are interpolated trilinearly (tent functions; constant
beyond the outermost nodes, so the weights always sum to 1 and every node is reproduced
exactly). For lenslet ``j`` the lateral weights of depth node ``z_g`` are taken not at the
source's own (x, y) but where lenslet j's chief ray through the source crosses depth ``z_g``
(the point at depth ``z_g`` whose focus lands on the same sensor pixel): between two calibration
depths each lenslet's PSF is interpolated along its chief ray, following the axial shear.
At a calibration depth this is plain trilinear interpolation, and for a lenslet without shear
(the central one) it is plain trilinear interpolation everywhere; elsewhere the two differ by
the shear across one depth step (≈ 2 px at full resolution for the corner lenslets of a CM² V2,
against ≈ 240 px between lateral nodes). It is what lets the forward operator sum the sheared
depth planes before convolving (:mod:`cm2optics.lsv.operators`).
"""

from __future__ import annotations

import numpy as np

from cm2optics.lsv.preprocess import Geometry

__all__ = ["axis_coordinate", "chief_ray_nodes", "coefficient_volume", "tent_pairs", "trilinear_coefficients"]


def axis_coordinate(values: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Continuous node index of ``values`` along a (sorted, possibly irregular) grid ``axis``,
    clamped to [0, n − 1]."""
    axis = np.asarray(axis, float)
    if len(axis) == 1:
        return np.zeros_like(np.asarray(values, float))
    return np.interp(np.asarray(values, float), axis, np.arange(len(axis), dtype=float))


def tent_pairs(u: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower node, upper node and the upper node's weight for continuous indices ``u``."""
    u = np.clip(np.asarray(u, float), 0, n - 1)
    lo = np.minimum(np.floor(u).astype(np.int64), max(n - 2, 0))
    t = u - lo
    hi = np.minimum(lo + 1, n - 1)
    return lo, hi, t


def trilinear_coefficients(
    coefficients: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray], x_mm, y_mm, z_mm
) -> np.ndarray:
    """Plain trilinear interpolation of ``coefficients`` (K, nz, ny, nx) on grid ``axes``
    (x, y, z in mm) at the points (x, y, z): an array (…, K)."""
    xs, ys, zs = axes
    x, y, z = np.broadcast_arrays(np.asarray(x_mm, float), np.asarray(y_mm, float), np.asarray(z_mm, float))
    K, nz, ny, nx = coefficients.shape
    xl, xh, tx = tent_pairs(axis_coordinate(x, xs), nx)
    yl, yh, ty = tent_pairs(axis_coordinate(y, ys), ny)
    zl, zh, tz = tent_pairs(axis_coordinate(z, zs), nz)
    out = np.zeros(x.shape + (K,))
    for zi, wz in ((zl, 1 - tz), (zh, tz)):
        for yi, wy in ((yl, 1 - ty), (yh, ty)):
            for xi, wx in ((xl, 1 - tx), (xh, tx)):
                out += (wz * wy * wx)[..., None] * np.moveaxis(coefficients[:, zi, yi, xi], 0, -1)
    return out


def chief_ray_nodes(
    geometry: Geometry,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    lenslet: int,
    x_mm,
    y_mm,
    z_mm,
) -> tuple[np.ndarray, np.ndarray]:
    """The eight nodes and weights of lenslet ``lenslet``'s interpolation at sources (x, y, z).

    Returns ``nodes`` (…, 8, 3) as (iz, iy, ix) and ``weights`` (…, 8), summing to 1.
    """
    xs, ys, zs = axes
    x, y, z = np.broadcast_arrays(np.asarray(x_mm, float), np.asarray(y_mm, float), np.asarray(z_mm, float))
    focus = geometry.focus(x, y, z)[..., lenslet, :]
    zl, zh, tz = tent_pairs(axis_coordinate(z, zs), len(zs))
    nodes, weights = [], []
    for zi, wz in ((zl, 1 - tz), (zh, tz)):
        zg = zs[zi]
        reference = focus - geometry.offsets(zg)[..., lenslet, :]
        xy = geometry.object_from_sensor(reference, zg)
        xl, xh, tx = tent_pairs(axis_coordinate(xy[..., 0], xs), len(xs))
        yl, yh, ty = tent_pairs(axis_coordinate(xy[..., 1], ys), len(ys))
        for yi, wy in ((yl, 1 - ty), (yh, ty)):
            for xi, wx in ((xl, 1 - tx), (xh, tx)):
                nodes.append(np.stack([zi, yi, xi], axis=-1))
                weights.append(wz * wy * wx)
    return np.stack(nodes, axis=-2), np.stack(weights, axis=-1)


def coefficient_volume(
    coefficients: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    z_mm: np.ndarray,
) -> np.ndarray:
    """Trilinear coefficient volumes (K, nz, ny, nx) on the grid x × y × z (1-D axes, mm)."""
    z, y, x = np.meshgrid(z_mm, y_mm, x_mm, indexing="ij")
    return np.moveaxis(trilinear_coefficients(coefficients, axes, x, y, z), -1, 0)
