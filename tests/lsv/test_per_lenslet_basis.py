"""A per-lenslet basis (each lenslet its own K single-lenslet PSFs, stored as one block-diagonal
basis of J·K focus arrays): the decomposition against per-lenslet SVDs, and every path (dense
forward/adjoint, naive reference, sparse) against the same node PSFs written as a shared basis."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_lsv_operators import GRIDS, SENSOR, _check_adjoint_and_naive, synthetic_model

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.scan import ScanError
from cm2optics.lsv.build import model_from_crops
from cm2optics.lsv.decompose import decompose, decompose_per_lenslet
from cm2optics.lsv.model import load_model


def _lenslet_crops(seed: int = 0, N: int = 14, J: int = 3, ranks=(2, 3, 1)) -> np.ndarray:
    """(N, J, 6, 7) crops: lenslet j a random mix of its own ``ranks[j]`` patterns, scaled by 1, 2, 3…"""
    rng = np.random.default_rng(seed)
    crops = np.zeros((N, J, 6, 7))
    for j, r in enumerate(ranks):
        patterns = rng.normal(size=(r, 6, 7))
        crops[:, j] = (j + 1) * np.einsum("nr,rab->nab", rng.normal(size=(N, r)), patterns)
    return crops.astype(np.float32)


def test_per_lenslet_decomposition_is_each_lenslets_svd_in_one_orthonormal_block_basis():
    crops = _lenslet_crops()
    dec = decompose_per_lenslet(crops, rank=3)
    K, J = dec.basis.shape[:2]
    assert K == 2 + 3 + 1  # a lenslet whose foci span fewer than 3 dimensions keeps fewer terms
    lit = np.abs(dec.basis).reshape(K, J, -1).max(axis=2) > 0
    assert (lit.sum(axis=1) == 1).all()  # every term lights one lenslet
    B = dec.basis.reshape(K, -1).astype(np.float64)
    np.testing.assert_allclose(B @ B.T, np.eye(K), atol=1e-5)
    expected = np.sort(
        np.concatenate(
            [np.linalg.svd(crops[:, j].reshape(len(crops), -1), compute_uv=False)[:r] for j, r in enumerate((2, 3, 1))]
        )
    )[::-1]
    np.testing.assert_allclose(dec.singular_values[:K], expected, rtol=1e-5)
    assert np.all(np.diff(dec.singular_values[:K]) <= 0)
    X = crops.reshape(len(crops), -1).astype(np.float64)
    np.testing.assert_allclose(dec.coefficients.astype(np.float64) @ B, X, atol=1e-4 * np.abs(X).max())
    for k in (1, 3, K):  # the errors against the number of terms kept, in this ordering
        residual = X - (X @ B[:k].T) @ B[:k]
        assert dec.nmse[k] == pytest.approx((residual**2).sum() / (X**2).sum(), abs=1e-6)
    # one basis of focus arrays needs all 6 terms for what each lenslet holds in its own 3 or fewer
    assert decompose(crops, 3).nmse[3] > 0.05 > dec.nmse[K]


def test_rank_one_per_lenslet_keeps_each_lenslets_strongest_term():
    crops = _lenslet_crops(seed=1)
    dec = decompose_per_lenslet(crops, rank=1)
    assert dec.basis.shape[0] == 3
    for j in range(3):
        block = dec.basis[:, j].reshape(3, -1)
        top = np.linalg.svd(crops[:, j].reshape(len(crops), -1).astype(np.float64))[2][0]
        kept = block[np.abs(block).max(axis=1) > 0]
        assert len(kept) == 1 and abs(float(kept[0] @ top)) == pytest.approx(1.0, abs=1e-5)


def _as_per_lenslet(model):
    """The same node PSFs as a per-lenslet basis: term (j, k) is basis PSF k in lenslet j only,
    with coefficient k's map."""
    K, J = model.basis.shape[:2]
    basis = np.zeros((J * K, J) + model.basis.shape[2:], np.float32)
    for j in range(J):
        basis[j * K : (j + 1) * K, j] = model.basis[:, j]
    return replace(model, basis=basis, coefficients=np.tile(model.coefficients, (J, 1, 1, 1)))


@pytest.mark.parametrize("kind", ["diag", "general"])
def test_a_per_lenslet_basis_runs_every_path_at_a_shared_basis_cost(kind, tmp_path):
    shared = synthetic_model(kind)
    model = _as_per_lenslet(shared)
    K, J = shared.basis.shape[:2]
    assert [list(model.lenslet_terms(j)) for j in range(J)] == [list(range(j * K, (j + 1) * K)) for j in range(J)]
    assert all(len(shared.lenslet_terms(j)) == K for j in range(J))
    op, op_shared = model.operator(), shared.operator()
    x, Ax = _check_adjoint_and_naive(model, op, seed=3)  # ⟨Ax, y⟩ = ⟨x, Aᵀy⟩ and the naive J·K·nz convolutions
    np.testing.assert_allclose(Ax, op_shared.forward(x), atol=1e-5 * np.abs(Ax).max())
    y = np.random.default_rng(4).normal(size=SENSOR).astype(np.float32)
    np.testing.assert_allclose(op.adjoint(y), op_shared.adjoint(y), atol=1e-5 * np.abs(op.adjoint(y)).max())
    # the operator keeps each lenslet's K patches (as the shared basis) and its own K coefficient maps
    nodes = int(np.prod(shared.coefficients.shape[1:]))
    assert op.memory_bytes() - op_shared.memory_bytes() == (J - 1) * K * nodes * 4
    emitters = Emitters(np.array([0.0, 300.0]), np.array([0.0, -200.0]), np.array([0.0, 80.0]), np.zeros(2), np.ones(2))
    sparse = model.forward_sparse(emitters, subpixel_steps=None)
    np.testing.assert_allclose(
        sparse, shared.forward_sparse(emitters, subpixel_steps=None), atol=1e-5 * np.abs(sparse).max()
    )
    loaded = load_model(model.save(tmp_path / "per_lenslet.h5"))  # the model format is unchanged
    assert [list(loaded.lenslet_terms(j)) for j in range(J)] == [list(model.lenslet_terms(j)) for j in range(J)]


def test_an_epsf_model_with_a_per_lenslet_basis_images_as_its_shared_basis():
    from test_lsv_epsf import epsf_model

    shared = epsf_model("general")
    model = _as_per_lenslet(shared)
    grid = GRIDS["coarser"]
    x = np.random.default_rng(5).random(grid.shape).astype(np.float32)
    dense = model.forward(x, grid)  # the ePSF operator: the whole-pixel operator of the fine model
    np.testing.assert_allclose(dense, shared.forward(x, grid), atol=1e-5 * np.abs(dense).max())
    point = model.point_image(0.2, -0.3, 0.05)
    np.testing.assert_allclose(point, shared.point_image(0.2, -0.3, 0.05), atol=1e-6 * np.abs(point).max())


def test_an_epsf_estimated_from_whole_pixel_frames_refuses_a_per_lenslet_basis():
    shared = synthetic_model()
    crops = _lenslet_crops(N=36, J=4, ranks=(2, 2, 1, 3))[:, :, :4, :4]
    grid_index = np.array([[ix, iy, iz] for iz in range(3) for iy in range(3) for ix in range(4)])
    with pytest.raises(ScanError, match="a per-lenslet basis needs fine crops"):
        model_from_crops(
            crops,
            grid_index,
            shared.axes,
            shared.geometry,
            rank=2,
            sensor_shape=SENSOR,
            pixel_um=20.0,
            trim=None,
            oversample=2,
            frames=(None, None),  # whole-pixel frames: the ePSF basis would be estimated jointly
            per_lenslet=True,
        )


def test_lenslet_by_lenslet_products_and_gram_equal_the_dense_ones():
    from cm2optics.lsv.decompose import basis_gram, lenslet_blocks, products

    crops = _lenslet_crops(seed=2)
    basis = decompose_per_lenslet(crops, rank=3).basis
    blocks = lenslet_blocks(basis)
    assert [len(b) for b in blocks] == [2, 3, 1] and lenslet_blocks(decompose(crops, 3).basis) is None
    np.testing.assert_allclose(products(crops, basis, blocks), products(crops, basis), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(basis_gram(basis, blocks), basis_gram(basis), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(basis_gram(basis, blocks), np.eye(6), atol=1e-5)


@pytest.mark.parametrize("per_lenslet", [False, True])
def test_projection_on_the_basis_keeps_the_models_own_patches_and_leaves_an_orthogonal_residual(per_lenslet):
    from cm2optics.lsv.sparse import place_patches

    model = synthetic_model("general")
    model = _as_per_lenslet(model) if per_lenslet else model
    own = model.focus_patches(0.2, -0.3, 0.05)  # in the basis's span: kept
    np.testing.assert_allclose(model.project(own), own, atol=1e-5 * np.abs(own).max())
    np.testing.assert_allclose(
        place_patches(model, own, 0.2, -0.3, 0.05), model.point_image(0.2, -0.3, 0.05), atol=1e-12
    )
    x = np.random.default_rng(7).normal(size=model.basis.shape[1:])
    residual = x - model.project(x)
    for j in range(model.n_lenslets):  # orthogonal to the terms lit in each lenslet, there
        terms = model.basis[model.lenslet_terms(j), j].reshape(len(model.lenslet_terms(j)), -1)
        np.testing.assert_allclose(terms @ residual[j].ravel(), 0, atol=1e-8 * np.abs(x).sum())
    with pytest.raises(ValueError, match="patches"):
        model.project(x[:, :-1])
