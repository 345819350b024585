"""The naive evaluation of the LSV forward model: one scipy FFT convolution per (k, z, lenslet).

The model in the paper's form (Eq. 2), lenslet by lenslet: every depth plane, splatted onto the
sensor grid (``R_z``) and shifted onto lenslet j's chief rays (``T_{s_j(z)}``, Keys cubic), is
multiplied by the coefficient map of basis PSF k at those sensor positions and convolved with
the basis PSF's patch for lenslet j:

    g = Σ_j Σ_z Σ_k fftconvolve(M_jk(·, z) · T_{s_j(z)} R_z O_z, P_jk)

in float64, with nothing of :mod:`cm2optics.lsv.operators`' factorisation: the coefficient maps
are interpolated pixel by pixel from the geometry and the calibration grid, every (k, z, j) is its
own full convolution. The plane splat and the shifts come from the operator (they define the
model's sampling). This is the reference the fast operator is checked against (tests) and
timed against (``benchmarks/bench_lsv.py``).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from scipy.signal import fftconvolve

from cm2optics.lsv.interpolate import axis_coordinate, tent_pairs
from cm2optics.lsv.kernels import TAPS, shift_weights, split_shift
from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.operators import LSVOperator

__all__ = ["coefficient_map", "reference_forward", "shifted_plane"]


def coefficient_map(
    operator: LSVOperator, z: int, j: int, region: tuple[int, int, int, int], k: int | None = None
) -> np.ndarray:
    """Coefficients of lenslet j for depth plane z on the canvas pixels ``region`` =
    (r0, r1, c0, c1): trilinear along the chief rays, from the model's interpolation grid. All K maps
    (K, rows, cols), or basis PSF ``k``'s alone (rows, cols)."""
    model = operator.model
    ks = slice(None) if k is None else slice(k, k + 1)
    out = None
    for a, weights in _map_weights(operator, z, j, region):
        coefficients = model.lenslet_coefficients(j)[ks, weights[0]].astype(np.float64)  # (k, ny, nx)
        if weights[1] == "separable" and len(weights) == 5:
            term = np.einsum("rx,kyx,cy->krc", weights[2], coefficients, weights[3], optimize=True)
        elif weights[1] == "separable":
            term = np.einsum("ry,kyx,cx->krc", weights[2], coefficients, weights[3], optimize=True)
        else:
            nodes, tents = weights[2], weights[3]
            term = sum(tents[t] * coefficients[:, nodes[t][0], nodes[t][1]] for t in range(4))
        out = a * term if out is None else out + a * term
    return out if k is None else out[0]


def _map_weights(operator: LSVOperator, z: int, j: int, region: tuple[int, int, int, int]) -> list:
    """Per depth node: its weight and the lateral tents on ``region`` (separable: row and column
    tent matrices; otherwise: four nodes and weights per pixel)."""
    model = operator.model
    geometry = model.geometry
    xs, ys, zs = model.interpolation_axes
    r0, r1, c0, c1 = region
    z_mm = float(operator.z_mm[z])
    lo, hi, t = tent_pairs(axis_coordinate(np.array(z_mm), zs), len(zs))
    rows = np.arange(r0, r1) + operator.canvas_origin[j, 0]
    cols = np.arange(c0, c1) + operator.canvas_origin[j, 1]
    out = []
    for gz, a in ((int(lo), 1.0 - float(t)), (int(hi), float(t))):
        if a == 0:
            continue
        zg = zs[gz]
        A = geometry.A(zg)
        reference = geometry.r0(zg) + geometry.offsets(zg)[j]
        if A[0, 0] == 0 and A[1, 1] == 0:  # rows follow y, columns follow x
            wy = _tents(axis_coordinate((rows - reference[0]) / A[0, 1], ys), len(ys))
            wx = _tents(axis_coordinate((cols - reference[1]) / A[1, 0], xs), len(xs))
            out.append((a, (gz, "separable", wy, wx)))
        elif A[0, 1] == 0 and A[1, 0] == 0:  # rows follow x, columns follow y: transpose the grid
            wx = _tents(axis_coordinate((rows - reference[0]) / A[0, 0], xs), len(xs))
            wy = _tents(axis_coordinate((cols - reference[1]) / A[1, 1], ys), len(ys))
            out.append((a, (gz, "separable", wx, wy, "transposed")))
        else:
            p = np.stack(np.meshgrid(rows, cols, indexing="ij"), -1).astype(float)
            xy = geometry.object_from_sensor(p - geometry.offsets(zg)[j], zg)
            xl, xh, tx = tent_pairs(axis_coordinate(xy[..., 0], xs), len(xs))
            yl, yh, ty = tent_pairs(axis_coordinate(xy[..., 1], ys), len(ys))
            nodes = [(yl, xl), (yl, xh), (yh, xl), (yh, xh)]
            tents = [(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx]
            out.append((a, (gz, "pixels", nodes, tents)))
    return out


def _tents(u: np.ndarray, n: int) -> np.ndarray:
    """(len(u), n) tent weights of every node at continuous node indices ``u``."""
    return np.clip(1.0 - np.abs(u[:, None] - np.arange(n)[None, :]), 0.0, None)


def shifted_plane(operator: LSVOperator, plane: np.ndarray, z: int, j: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Plane (Hp, Wp) shifted by s_j(z) with the Keys taps; returns the shifted array and the
    canvas pixel of its [0, 0]."""
    n, eps = split_shift(operator.shifts[z, j])
    wr, wc = shift_weights(eps[0]), shift_weights(eps[1])
    Hp, Wp = plane.shape
    tmp = np.zeros((Hp + 3, Wp))
    for t, weight in zip(TAPS, wr, strict=True):
        tmp[1 + t : 1 + t + Hp] += weight * plane
    out = np.zeros((Hp + 3, Wp + 3))
    for t, weight in zip(TAPS, wc, strict=True):
        out[:, 1 + t : 1 + t + Wp] += weight * tmp
    return out, (int(n[0]) - 1, int(n[1]) - 1)


def reference_forward(
    model: LSVModel,
    operator: LSVOperator,
    volume: np.ndarray,
    pairs: Iterable[tuple[int, int]] | None = None,
) -> np.ndarray:
    """Sensor image (float64) of ``volume`` (z, y, x) summed over the (k, z) ``pairs`` (all by
    default), each pair as J full FFT convolutions."""
    H, W = model.sensor_shape
    h, w = model.patch_shape
    image = np.zeros((H, W))
    nz = volume.shape[0]
    if pairs is None:
        pairs = [(k, z) for z in range(nz) for k in range(model.rank)]
    shifted: dict[tuple[int, int], tuple[np.ndarray, tuple[int, int]]] = {}
    maps: dict[tuple[int, int], list] = {}
    for k, z in pairs:
        plane = operator._splat(torch.as_tensor(volume[z], dtype=torch.float32), z).double().numpy()
        if not plane.any():
            continue
        for j in range(model.n_lenslets):
            if (z, j) not in shifted:
                shifted[(z, j)] = shifted_plane(operator, plane, z, j)
            data, (r, c) = shifted[(z, j)]
            region = (r, r + data.shape[0], c, c + data.shape[1])
            if (z, j) not in maps:
                maps[(z, j)] = _map_weights(operator, z, j, region)
            weighted = _apply_map(model, maps[(z, j)], k, j) * data
            out = fftconvolve(weighted, model.basis[k, j].astype(np.float64))
            top = r + int(operator.canvas_origin[j, 0]) - h // 2
            left = c + int(operator.canvas_origin[j, 1]) - w // 2
            rs, re = max(top, 0), min(top + out.shape[0], H)
            cs, ce = max(left, 0), min(left + out.shape[1], W)
            if rs < re and cs < ce:
                image[rs:re, cs:ce] += out[rs - top : re - top, cs - left : ce - left]
    return image


def _apply_map(model: LSVModel, weights: list, k: int, j: int) -> np.ndarray:
    """Basis PSF k's coefficient map of lenslet j from cached :func:`_map_weights`."""
    out = None
    for a, w in weights:
        coefficients = model.lenslet_coefficients(j)[k, w[0]].astype(np.float64)  # (ny, nx)
        if w[1] == "separable" and len(w) == 5:
            term = w[2] @ coefficients.T @ w[3].T
        elif w[1] == "separable":
            term = w[2] @ coefficients @ w[3].T
        else:
            nodes, tents = w[2], w[3]
            term = sum(tents[t] * coefficients[nodes[t][0], nodes[t][1]] for t in range(4))
        out = a * term if out is None else out + a * term
    return out
