"""Displacement interpolation between neighbouring PSFs (cm2optics.lsv.warp): the moments, the
transport map, a known-answer blend of two Gaussian foci, and a toy model whose PSF's elongation
changes across the field (off-node points reproduced with the warp, not without)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from cm2optics.lsv.epsf import fine_model
from cm2optics.lsv.epsf_validate import turn_check
from cm2optics.lsv.lsi import lsi_model
from cm2optics.lsv.model import load_model
from cm2optics.lsv.preprocess import Geometry
from cm2optics.lsv.rotation import basis_projector, rotate_patches, rotated_blend, turn_matrices
from cm2optics.lsv.warp import (
    affine_resample,
    displacement_blend,
    focus_moments,
    log_euclidean_mean,
    transport_maps,
)

S = 4  # oversample
PATCH = 16  # px
AXIS_MM = np.array([0.05, -0.45])  # the lenslet's axis in object space (off every node)


def _gaussian(shape: tuple[int, int], centre, covariance) -> np.ndarray:
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    d = np.stack([r - centre[0], c - centre[1]], -1)
    q = np.einsum("...i,ij,...j->...", d, np.linalg.inv(covariance), d)
    p = np.exp(-0.5 * q)
    return p / p.sum()


def test_affine_resample_moves_samples_where_the_map_says():
    """Known answers: a whole-sample shift and a quarter turn about the centre move samples
    exactly; a general map agrees with bicubic sampling at the map's coordinates, written out."""
    rng = np.random.default_rng(3)
    patch = torch.as_tensor(rng.random((1, 15, 15)), dtype=torch.float64)
    shifted = affine_resample(patch, np.eye(2), np.array([7.0, 7.0]), np.array([9.0, 6.0]))
    np.testing.assert_allclose(shifted[0, :13, 1:], patch[0, 2:, :14], atol=1e-12)  # out (r, c) ← in (r + 2, c − 1)
    assert float(shifted[0, 13:].abs().max()) < 1e-12  # beyond the input: zero
    quarter = np.array([[0.0, 1.0], [-1.0, 0.0]])  # out (r, c) ← in (7 + (c − 7), 7 − (r − 7))
    turned = affine_resample(patch, quarter, np.array([7.0, 7.0]), np.array([7.0, 7.0]))
    np.testing.assert_allclose(turned[0], torch.rot90(patch[0], 1, (0, 1)), atol=1e-12)
    patches = torch.as_tensor(rng.random((3, 12, 17)), dtype=torch.float64)  # not square: rows ≠ cols
    matrices = np.eye(2) + 0.3 * rng.normal(size=(3, 2, 2))
    out_centres, in_centres = rng.uniform(3, 9, (3, 2)), rng.uniform(3, 9, (3, 2))
    r, c = np.mgrid[0:12, 0:17].astype(float)
    d = np.stack([r, c], -1)[None] - out_centres[:, None, None]
    source = in_centres[:, None, None] + np.einsum("mij,mrcj->mrci", matrices, d)
    grid = torch.as_tensor(np.stack([2 * source[..., 1] / 16 - 1, 2 * source[..., 0] / 11 - 1], -1))
    reference = torch.nn.functional.grid_sample(patches[:, None], grid, mode="bicubic", align_corners=True)[:, 0]
    np.testing.assert_allclose(affine_resample(patches, matrices, out_centres, in_centres), reference, atol=1e-10)


def test_moments_and_transport_map_of_gaussians():
    cov = np.array([[9.0, 2.0], [2.0, 4.0]])
    centroid, covariance, total = focus_moments(torch.as_tensor(_gaussian((64, 64), (30.5, 33.0), cov))[None])
    np.testing.assert_allclose(centroid[0], [30.5, 33.0], atol=1e-6)
    np.testing.assert_allclose(covariance[0], cov / 2, rtol=1e-4)  # the squared PSF: half the covariance
    assert total[0] > 0
    target = np.array([[3.0, -1.0], [-1.0, 5.0]])
    T = transport_maps(cov, target)
    np.testing.assert_allclose(T @ cov @ T, target, atol=1e-9)
    np.testing.assert_allclose(T, T.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(T) > 0)
    np.testing.assert_allclose(log_euclidean_mean(np.stack([cov, cov])[None], np.array([[0.3, 0.7]]))[0], cov)


@pytest.mark.parametrize(
    ("first", "second"),
    [
        (np.diag([36.0, 4.0]), np.diag([4.0, 36.0])),  # astigmatic focus turning from vertical to horizontal
        (np.diag([4.0, 4.0]), np.diag([25.0, 25.0])),  # a defocus blur growing
    ],
)
def test_displacement_blend_gives_the_intermediate_shape(first, second):
    """Known answer: two Gaussian foci blended with weights (1 − t, t) become the Gaussian of the
    log-Euclidean mean covariance at the weighted mean centre; a linear blend is a ghosted double."""
    shape, t = (64, 64), 0.3
    a, b = _gaussian(shape, (30.0, 31.0), first), _gaussian(shape, (33.0, 32.0), second)
    mean = np.diag(np.exp((1 - t) * np.log(np.diag(first)) + t * np.log(np.diag(second))))
    truth = _gaussian(shape, (30.0 + 3 * t, 31.0 + t), mean)
    pair = torch.as_tensor(np.stack([a, b]))[None]
    warped = displacement_blend(pair, np.array([[1 - t, t]])).numpy()[0]
    linear = (1 - t) * a + t * b

    def error(m):
        return np.linalg.norm(m - truth) / np.linalg.norm(truth)

    assert error(warped) < 0.02 and error(linear) > 0.15, (error(warped), error(linear))
    assert warped.sum() == pytest.approx(1.0, abs=1e-3)  # flux kept


@pytest.mark.parametrize("warp", [False, True])
def test_blends_skip_zero_weight_neighbours_without_changing_the_result(warp):
    """rotated_blend synthesises and resamples only neighbours with weight: the coefficients equal
    those of every neighbour turned (and warped), blended and re-projected, written out here."""
    rng = np.random.default_rng(5)
    K, L, M, n = 6, 8, 5, 24
    basis = np.stack([_gaussian((n, n), rng.uniform(9, 15, 2), np.diag(rng.uniform(2, 9, 2))) for _ in range(K)])
    neighbours = rng.uniform(0.2, 1.0, (M, L, K))
    weights = rng.uniform(0.1, 1.0, (M, L)) * (rng.random((M, L)) < 0.5)
    weights[:, 0] += 0.1  # every blend has a neighbour with weight
    weights /= weights.sum(axis=1, keepdims=True)
    angles = rng.uniform(-0.5, 0.5, (M, L))
    pivot = np.array([11.5, 12.5])
    B, projector = basis_projector(basis)
    out = rotated_blend((B, projector), (n, n), neighbours, weights, angles, pivot, warp=warp)
    psfs = torch.as_tensor(neighbours.reshape(-1, K), dtype=torch.float32) @ B
    if warp:
        rotation = turn_matrices(angles)
        turns = np.concatenate([rotation, np.broadcast_to(pivot, (M, L, 2))[..., None]], -1)
        blended = displacement_blend(psfs.reshape(M, L, n, n), weights, turns).reshape(M, -1)
    else:
        turned = rotate_patches(psfs.reshape(-1, n, n), angles.reshape(-1), pivot).reshape(M, L, -1)
        blended = torch.einsum("mlp,ml->mp", turned, torch.as_tensor(weights, dtype=torch.float32))
    reference = (blended @ projector.T).numpy()
    np.testing.assert_allclose(out, reference, rtol=0, atol=1e-5 * np.abs(reference).max())
    assert np.abs(out - np.einsum("mlk,ml->mk", neighbours, weights)).max() > 1e-3  # not the plain blend


def _geometry() -> Geometry:
    """One lenslet with its axis at AXIS_MM; magnification 60 px/mm at z = 0, changing by 10 %/mm."""
    mirror = np.array([[0.0, -1.0], [-1.0, 0.0]])
    A_poly = np.stack([60.0 * mirror, 6.0 * mirror])
    r0 = np.array([200.0, 210.0]) - 60.0 * mirror @ AXIS_MM
    r0_poly = np.stack([r0, -6.0 * mirror @ AXIS_MM])
    return Geometry(r0_poly=r0_poly, A_poly=A_poly, o_poly=np.zeros((1, 1, 2)), rows=1, cols=1)


def _psf(x: float, y: float, z: float) -> np.ndarray:
    """(1, h·S, w·S) fine PSF of unit flux: a Gaussian whose log-elongation, log(σ_row/σ_col),
    grows linearly with the distance from the lenslet's axis along x (long along the columns on
    one side, along the rows on the other, as an astigmatic focus that field curvature moves
    through the plane), and whose size grows with |z − 0.05 mm| (defocus): its log-covariance is
    affine between lateral nodes, where displacement interpolation is exact."""
    grow = 1.0 + abs(z - 0.05)
    sigma = 0.9 * np.exp((x - AXIS_MM[0]) * np.array([1.0, -1.0])) * grow * S
    n = PATCH * S
    r, c = np.mgrid[0:n, 0:n] - S * (PATCH // 2)
    psf = np.exp(-0.5 * ((r / sigma[0]) ** 2 + (c / sigma[1]) ** 2))
    return (psf / psf.sum())[None].astype(np.float32)  # unit flux


@pytest.fixture(scope="module")
def toy(grid_toy):
    axes = (np.linspace(-0.95, 1.05, 5), np.linspace(-1.45, 0.55, 5), np.array([-0.2, 0.0, 0.2]))
    return grid_toy(_psf, axes, _geometry(), S)


def _error(model, points) -> float:
    errors = []
    for x, y, z in points:
        truth = _psf(x, y, z)
        patch = model.focus_patches(x, y, z) / model.scale
        errors.append(np.linalg.norm(patch - truth) / np.linalg.norm(truth))
    return float(np.mean(errors))


def test_warping_the_neighbours_reproduces_a_psf_whose_shape_changes_with_the_field(toy, tmp_path):
    """Known answer: where the PSF's log-covariance is affine in the field, the warp blends the
    neighbours into the source's shape (off-node points of the refined grid); a linear blend of
    differently elongated foci is a double shape."""
    plain, _, _ = toy
    warped = replace(plain, refine=2, warp_shapes=True)
    xs, ys, zs = plain.axes
    points = [(xs[3] + 0.25, ys[4], zs[1]), (xs[0] + 0.25, ys[0] + 0.25, zs[0]), (xs[2] + 0.25, ys[1], zs[2])]
    error_plain, error_warped = _error(plain, points), _error(warped, points)
    # the warped blend is re-projected on the basis, which the nodes' own shapes span: a floor
    assert error_plain > 0.05 and error_warped < 0.5 * error_plain, (error_plain, error_warped)
    nodes = [(xs[1], ys[3], zs[2]), (xs[4], ys[0], zs[0])]
    assert _error(warped, nodes) == pytest.approx(_error(plain, nodes), abs=1e-4)
    loaded = load_model(warped.save(tmp_path / "warped.h5"))
    assert loaded.warp_shapes and not loaded.rotate_aberrations
    np.testing.assert_allclose(loaded.lenslet_coefficients(0), warped.lenslet_coefficients(0), atol=1e-6)
    assert not lsi_model(loaded).warp_shapes  # the shift-invariant baseline has no neighbours
    fine = fine_model(loaded)  # the ePSF operator's fine-grid model keeps the warped coefficients
    np.testing.assert_allclose(fine.lenslet_coefficients(0), warped.lenslet_coefficients(0), atol=1e-6)


def test_the_scan_decides_for_the_warp_where_the_shape_changes(toy):
    """turn_check (what `cm2 lsv build --warp auto` decides by): nodes left out, predicted from
    their lateral neighbours, are predicted far better warped than blended linearly."""
    _, crops, grid_index = toy
    check = turn_check(crops, grid_index, toy[0].axes, None, None, warp=True, n_heldout=6)
    assert check["n_heldout"] == 6
    assert check["nmse_warped"] < 0.2 * check["nmse_fixed_orientation"], check
    assert math.isfinite(check["nmse_fixed_orientation"])
