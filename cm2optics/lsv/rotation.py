"""Interpolation between lateral nodes that turns each PSF with the field azimuth.

A lenslet that is rotationally symmetric about its own axis images a field point at polar
position (ρ, φ) about that axis as the point at (ρ, 0), rotated by φ: the astigmatic and comatic
foci turn with the azimuth. Linear blending of two neighbouring nodes' PSFs of different
orientation makes a cross; here each neighbour's PSF is first turned by the difference of
azimuths about the focus of the lenslet's axis (:func:`axis_pivots`), then blended with the same
tent weights (along the focal surface if the model has one), and re-projected on the lenslet's
basis patches (least squares). This is done once per model, on the refined lateral grid of
:func:`~cm2optics.lsv.interpolate.refined_lenslet_coefficients`, so every path (point, sparse,
dense forward and adjoint, the naive reference) uses the turned coefficients through
:meth:`LSVModel.lenslet_coefficients` at the cost of the refined grid, no more.

Azimuths are measured on the sensor, as the direction of the focus's displacement from the image
of the lenslet's axis (``A(z)·((x, y) − a_j)``, (row, col)): a mirror-imaging geometry turns the
PSF the other way round in (x, y), not on the sensor. The lenslet's axis ``a_j`` (object x, y mm)
is the source position whose focus does not move with depth (a point on a lens's axis is imaged
onto that axis at every depth): least squares over the calibration depths. Housing vignetting
and a real lens's asymmetries break the symmetry; whether a scan follows it is decided by the
scan's own nodes, left out and predicted with and without the turn
(:func:`cm2optics.lsv.epsf_validate.turn_check`, ``cm2 lsv build --rotate auto``).

The same machinery carries the displacement interpolation of :mod:`cm2optics.lsv.warp`
(``warp=True``): each neighbour's PSF turned and warped to the interpolated focus shape in one
resampling, all eight neighbours (4 lateral × 2 depths) blended so, then re-projected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from cm2optics.lsv.focal_surface import FocalSurface
from cm2optics.lsv.interpolate import defocus_nodes, refine_axis, trilinear_coefficients
from cm2optics.lsv.preprocess import Geometry
from cm2optics.lsv.warp import affine_resample, displacement_blend

__all__ = [
    "AzimuthTurn",
    "axis_pivots",
    "basis_projector",
    "lenslet_axes",
    "rotate_patches",
    "rotated_blend",
    "rotated_lenslet_coefficients",
    "sensor_azimuth",
]

#: Patches turned per batch (bounds one batch's patches, sampling grid and turned copies to
#: ≈ 250 MB at 224² samples).
ROTATION_BATCH = 256


def lenslet_axes(geometry: Geometry, z_mm: np.ndarray) -> np.ndarray:
    """(J, 2) object (x, y) mm of each lenslet's axis: the source whose focus stays put over the
    depths ``z_mm`` (least squares of ``r0(z) + A(z)·a + o_j(z) = const``)."""
    z = np.asarray(z_mm, float)
    if len(z) < 2:
        raise ValueError("the lenslets' axes need ≥ 2 calibration depths (the focus's motion with depth)")
    A = geometry.A(z)  # (nz, 2, 2)
    base = geometry.r0(z)[:, None, :] + geometry.offsets(z)  # (nz, J, 2)
    # unknowns (a_x, a_y, c_row, c_col): A(z)·a − c = −base(z)
    rows = np.concatenate([A, -np.broadcast_to(np.eye(2), A.shape)], axis=-1).reshape(-1, 4)  # (nz·2, 4)
    singular = np.linalg.svd(rows, compute_uv=False)
    if singular[-1] <= 1e-9 * singular[0]:
        raise ValueError("the magnification does not change with depth: the lenslets' axes cannot be found")
    right = -np.swapaxes(base, 1, 2).reshape(len(z) * 2, -1)  # (nz·2, J): one column per lenslet
    solution, *_ = np.linalg.lstsq(rows, right, rcond=None)
    return solution[:2].T


def sensor_azimuth(geometry: Geometry, axis_mm: np.ndarray, x_mm, y_mm, z_mm) -> np.ndarray:
    """Azimuth (rad) on the sensor of the focus of sources (x, y, z) mm about the image of the
    lenslet axis ``axis_mm`` (x, y): ``atan2(col, row)`` of ``A(z)·((x, y) − axis)``."""
    x, y, z = np.broadcast_arrays(np.asarray(x_mm, float), np.asarray(y_mm, float), np.asarray(z_mm, float))
    d = np.stack([x - axis_mm[0], y - axis_mm[1]], axis=-1)
    s = np.einsum("...ab,...b->...a", geometry.A(z), d)
    return np.arctan2(s[..., 1], s[..., 0])


def rotate_patches(patches: torch.Tensor, angles: np.ndarray, centres: np.ndarray) -> torch.Tensor:
    """(M, h, w) patches each turned by ``angles`` (M,) rad about ``centres`` ((M, 2) or (2,),
    (row, col) samples), on the sensor's (row, col) axes (a displacement at azimuth
    ``atan2(col, row)`` moves to azimuth + angle); bicubic, zero outside."""
    return affine_resample(patches, np.swapaxes(turn_matrices(angles), -1, -2), centres, centres)


def turn_matrices(angles: np.ndarray) -> np.ndarray:
    """(…, 2, 2) rotations of (row, col) displacements by ``angles`` (…) rad: a displacement at
    azimuth ``atan2(col, row)`` moves to azimuth + angle."""
    cos, sin = np.cos(angles), np.sin(angles)
    return np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)


def basis_projector(basis: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """One lenslet's basis patches (K, h, w) as a (K, h·w) float32 matrix and its least-squares
    projector (the pseudo-inverse of its transpose, (K, h·w))."""
    B = torch.as_tensor(basis.reshape(basis.shape[0], -1), dtype=torch.float32)
    return B, torch.linalg.pinv(B.double().T, rtol=1e-6).float()


def rotated_blend(
    basis: tuple[torch.Tensor, torch.Tensor],
    shape: tuple[int, int],
    neighbours: np.ndarray,
    weights: np.ndarray,
    angles: np.ndarray,
    pivot: np.ndarray,
    warp: bool = False,
) -> np.ndarray:
    """Coefficients (M, K) of the blends ``Σ_l w_l · rot(Δφ_l)[Σ_k c_lk P_k]`` re-projected on the
    basis patches P (least squares; ``basis``: :func:`basis_projector`, patches of ``shape``),
    for ``neighbours`` (M, L, K) coefficient vectors, tent ``weights`` (M, L) and azimuth
    differences ``angles`` (M, L) rad, each PSF turned about ``pivot`` (row, col) samples
    (:func:`rotate_patches`). ``warp``: the turned PSFs blended by displacement interpolation
    (:func:`~cm2optics.lsv.warp.displacement_blend`) instead. Blends that neither turn nor (with
    ``warp``) mix two neighbours are the plain weighted sums of the coefficients (no
    re-projection)."""
    B, projector = basis
    K = B.shape[0]
    h, w = shape
    plain = np.einsum("mlk,ml->mk", neighbours, weights)
    changing = np.any((np.abs(angles) > 1e-9) & (weights > 0), axis=1)
    if warp:
        changing |= np.count_nonzero(weights > 1e-9, axis=1) > 1
    turning = np.nonzero(changing)[0]
    if len(turning) == 0:
        return plain
    out = plain.copy()
    L = neighbours.shape[1]
    step = max(1, ROTATION_BATCH // L)
    for start in range(0, len(turning), step):
        rows = turning[start : start + step]
        # only the neighbours with weight are synthesised and resampled (a blend's zero-weight ones add nothing)
        active = torch.as_tensor(np.flatnonzero(weights[rows].reshape(-1) > 0))
        c = torch.as_tensor(neighbours[rows].reshape(-1, K), dtype=torch.float32)
        psfs = torch.zeros((len(c), h * w), dtype=torch.float32)
        psfs[active] = c[active] @ B
        psfs = psfs.reshape(-1, h, w)
        if warp:
            rotation = turn_matrices(angles[rows])  # (m, L, 2, 2)
            turns = np.concatenate(
                [rotation, np.broadcast_to(np.asarray(pivot, float), rotation.shape[:-1])[..., None]], -1
            )
            blended = displacement_blend(psfs.reshape(len(rows), L, h, w), weights[rows], turns).reshape(len(rows), -1)
        else:
            turned = rotate_patches(psfs[active], angles[rows].reshape(-1)[active.numpy()], pivot)
            gain = torch.as_tensor(weights[rows].reshape(-1)[active.numpy()], dtype=torch.float32)
            blended = torch.zeros((len(rows), h * w), dtype=torch.float32)
            blended.index_add_(0, active // L, turned.reshape(len(active), -1) * gain[:, None])
        out[rows] = (blended @ projector.T).numpy()
    return out


def axis_pivots(
    coefficients: np.ndarray, basis: np.ndarray, axes: tuple[np.ndarray, np.ndarray, np.ndarray], lens_axes: np.ndarray
) -> np.ndarray:
    """(J, nz, 2) the sample (row, col) in each lenslet's basis patch where the focus of a source
    on its axis lies, per calibration depth: the centroid of the squared model PSF there (plain
    trilinear coefficients; a focus on the axis is symmetric about it; squared, so that the
    low-rank basis's faint far wings, which moved the plain centroid by up to 1.3 px on the
    9×9×11 traced scan, do not count). It differs from the chief ray's sample where the fitted
    geometry puts the foci slightly off (1–2 px for the outer lenslets of that scan), and the PSF
    turns about it, not about the chief ray."""
    K, J, h, w = basis.shape
    zs = np.asarray(axes[2], float)
    rows, cols = np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64)
    out = np.empty((J, len(zs), 2))
    for j in range(J):
        c = trilinear_coefficients(coefficients, axes, lens_axes[j, 0], lens_axes[j, 1], zs)  # (nz, K)
        psf = np.clip(np.tensordot(c, basis[:, j], axes=(1, 0)), 0.0, None) ** 2  # (nz, h, w)
        total = np.maximum(psf.sum(axis=(1, 2)), 1e-300)
        out[j, :, 0] = np.einsum("zrc,r->z", psf, rows) / total
        out[j, :, 1] = np.einsum("zrc,c->z", psf, cols) / total
    return out


def rotated_lenslet_coefficients(
    coefficients: np.ndarray,
    basis: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
    geometry: Geometry,
    surface: FocalSurface | None,
    refine: int,
    *,
    turn: bool = True,
    warp: bool = False,
) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """As :func:`~cm2optics.lsv.interpolate.refined_lenslet_coefficients` (along the focal
    surface if there is one, else at fixed depth), but with ``turn`` each lateral neighbour's PSF
    turned to the refined node's azimuth about the lenslet's axis before the blend, about the
    axis's focus (:func:`axis_pivots`), with ``warp`` all eight neighbours (4 lateral × 2 depths)
    blended by displacement interpolation (:mod:`cm2optics.lsv.warp`), and the blend re-projected
    on the lenslet's basis patches (module docstring). ``basis`` (K, J, h, w). Returns the
    refined axes (x, y, z mm) and (J, K, nz, ny', nx') float32."""
    xs, ys, zs = (np.asarray(a, float) for a in axes)
    J = basis.shape[1]
    K = coefficients.shape[0]
    fine = (refine_axis(xs, refine), refine_axis(ys, refine), zs)
    z, y, x = np.meshgrid(fine[2], fine[1], fine[0], indexing="ij")
    flat = surface if surface is not None else FocalSurface(np.zeros((J, 4)), np.zeros(J))
    if turn:
        lens_axes = lenslet_axes(geometry, zs)
        pivots = axis_pivots(coefficients, basis, axes, lens_axes)
    else:
        pivots = np.zeros((J, len(zs), 2))
    out = np.empty((J, K) + z.shape, np.float32)
    for j in range(J):
        projector = basis_projector(basis[:, j])
        for iz in range(len(zs)):
            xz, yz, zz = x[iz].reshape(-1), y[iz].reshape(-1), z[iz].reshape(-1)
            nodes, weights = defocus_nodes(flat, axes, j, xz, yz, zz)  # (P, 8, 3): 4 lateral × 2 depths
            nodes, weights = nodes.reshape(-1, 4, 2, 3), weights.reshape(-1, 4, 2)
            values = np.moveaxis(coefficients[:, nodes[..., 0], nodes[..., 1], nodes[..., 2]], 0, -1)  # (P,4,2,K)
            angles = np.zeros(weights.shape[:2])
            if turn:
                target = sensor_azimuth(geometry, lens_axes[j], xz[:, None], yz[:, None], zz[:, None])
                node = sensor_azimuth(geometry, lens_axes[j], xs[nodes[..., 0, 2]], ys[nodes[..., 0, 1]], zz[:, None])
                angles = np.angle(np.exp(1j * (target - node)))  # wrapped to (−π, π]
            if warp:  # every neighbour its own shape
                neighbours, blend_weights = values.reshape(len(xz), 8, K), weights.reshape(-1, 8)
                angles = np.repeat(angles, 2, axis=1)
            else:  # each lateral neighbour's axial stack blended first
                blend_weights = weights.sum(-1)  # (P, 4)
                safe = np.where(blend_weights > 0, blend_weights, 1.0)[..., None]
                neighbours = np.einsum("plek,ple->plk", values, weights) / safe
            blended = rotated_blend(
                projector, basis.shape[2:], neighbours, blend_weights, angles, pivots[j, iz], warp=warp
            )  # (P, K)
            out[j, :, iz] = blended.T.reshape((K,) + x.shape[1:])
    return fine, out


@dataclass(frozen=True)
class AzimuthTurn:
    """What turning a lateral neighbour's PSFs needs: the geometry, the lenslets' axes (J, 2) mm
    (:func:`lenslet_axes`) and the axis foci's samples (J, nz, 2) per calibration depth
    (:func:`axis_pivots`)."""

    geometry: Geometry
    lens_axes: np.ndarray
    pivots: np.ndarray

    @classmethod
    def of_model(cls, model) -> AzimuthTurn:
        """The turn of an :class:`~cm2optics.lsv.model.LSVModel`'s own geometry and basis."""
        lens_axes = lenslet_axes(model.geometry, model.grid_z_mm)
        return cls(model.geometry, lens_axes, axis_pivots(model.coefficients, model.basis, model.axes, lens_axes))

    def __call__(self, patches: np.ndarray, source_xy, node_xy, z_mm: float, depth_index: int) -> np.ndarray:
        """Node PSFs ``patches`` (J, h, w) of a node at ``node_xy`` (mm) turned, lenslet by
        lenslet, to the azimuth of a source at ``source_xy`` (both at depth ``z_mm``, calibration
        depth ``depth_index`` for the pivots)."""
        J = len(patches)
        angles = np.array(
            [
                sensor_azimuth(self.geometry, self.lens_axes[j], *source_xy, z_mm)
                - sensor_azimuth(self.geometry, self.lens_axes[j], *node_xy, z_mm)
                for j in range(J)
            ]
        )
        turned = rotate_patches(
            torch.as_tensor(np.asarray(patches), dtype=torch.float32), angles, self.pivots[:, depth_index]
        )
        return turned.numpy().astype(patches.dtype, copy=False)
