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

from cm2optics.lsv.focal_surface import FocalSurface
from cm2optics.lsv.preprocess import Geometry

__all__ = [
    "axis_coordinate",
    "chief_ray_nodes",
    "coefficient_volume",
    "defocus_nodes",
    "refine_axis",
    "refined_lenslet_coefficients",
    "tent_pairs",
    "trilinear_coefficients",
]


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


def defocus_nodes(
    surface: FocalSurface,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    lenslet: int,
    x_mm,
    y_mm,
    z_mm,
) -> tuple[np.ndarray, np.ndarray]:
    """Eight nodes and weights of lenslet ``lenslet`` at sources (x, y, z) mm that follow the
    field curvature: the lateral tents at (x, y), and lateral node n's axial stack taken at the
    same defocus from the local best focus, ``z − z_best(x, y) + z_best(x_n, y_n)`` (mm).

    Returns ``nodes`` (…, 8, 3) as (iz, iy, ix) and ``weights`` (…, 8), summing to 1.
    """
    xs, ys, zs = axes
    x, y, z = np.broadcast_arrays(np.asarray(x_mm, float), np.asarray(y_mm, float), np.asarray(z_mm, float))
    defocus = z - surface.z_best(x, y, lenslet)
    xl, xh, tx = tent_pairs(axis_coordinate(x, xs), len(xs))
    yl, yh, ty = tent_pairs(axis_coordinate(y, ys), len(ys))
    nodes, weights = [], []
    for yi, wy in ((yl, 1 - ty), (yh, ty)):
        for xi, wx in ((xl, 1 - tx), (xh, tx)):
            depth = defocus + surface.z_best(xs[xi], ys[yi], lenslet)
            zl, zh, tz = tent_pairs(axis_coordinate(depth, zs), len(zs))
            for zi, wz in ((zl, 1 - tz), (zh, tz)):
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


def refine_axis(axis: np.ndarray, refine: int) -> np.ndarray:
    """The grid ``axis`` (mm) with every interval cut into ``refine`` equal steps."""
    axis = np.asarray(axis, float)
    if refine == 1 or len(axis) < 2:
        return axis
    steps = np.arange(refine) / refine
    inner = (axis[:-1, None] + np.diff(axis)[:, None] * steps[None, :]).ravel()
    return np.append(inner, axis[-1])


def refined_lenslet_coefficients(
    coefficients: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    surface: FocalSurface,
    refine: int,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """Each lenslet's coefficients (K, nz, ny, nx) interpolated along its focal surface
    (:func:`defocus_nodes`) onto the calibration grid with its lateral steps cut ``refine``
    times: returns the refined axes (x, y, z mm; z unchanged) and (J, K, nz, ny', nx') float32.
    At the calibration nodes the coefficients are the nodes' own."""
    xs, ys, zs = axes
    fine = (refine_axis(xs, refine), refine_axis(ys, refine), np.asarray(zs, float))
    z, y, x = np.meshgrid(fine[2], fine[1], fine[0], indexing="ij")
    out = np.empty((surface.n_lenslets, coefficients.shape[0]) + z.shape, np.float32)
    for j in range(surface.n_lenslets):
        nodes, weights = defocus_nodes(surface, axes, j, x, y, z)
        values = coefficients[:, nodes[..., 0], nodes[..., 1], nodes[..., 2]]  # (K, nz, ny', nx', 8)
        out[j] = np.einsum("k...e,...e->k...", values, weights)
    return fine, out
