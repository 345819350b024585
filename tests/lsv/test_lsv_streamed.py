"""The streamed (memory-bounded) build: crops on disk, a randomized SVD over chunks of positions,
the same model as the in-memory build up to the SVD's truncation."""

from __future__ import annotations

import numpy as np
import pytest

from cm2optics.lsv.build import build_model
from cm2optics.lsv.crop_store import CropStore, crop_array, position_chunks
from cm2optics.lsv.decompose import decompose, streamed_decompose
from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan


def _store(crops: np.ndarray, chunk: int) -> CropStore:
    store = CropStore.create(crops.shape, chunk)
    for n, crop in enumerate(crops):
        store[n] = crop
    return store


def test_a_store_reads_back_what_was_written_in_chunks_and_windows():
    crops = np.random.default_rng(1).random((7, 2, 6, 8), dtype=np.float32)
    store = _store(crops, chunk=3)
    assert [(start, len(block)) for start, block in position_chunks(store)] == [(0, 3), (3, 3), (6, 1)]
    np.testing.assert_array_equal(store[:], crops)
    view = store.windowed(slice(1, 5), slice(2, 8)).windowed(slice(1, 3), slice(0, 4))
    np.testing.assert_array_equal(view[:], crops[:, :, 2:4, 2:6])
    assert view.shape == (7, 2, 2, 4)
    np.testing.assert_array_equal(view[4, 1], crops[4, 1, 2:4, 2:6])
    np.testing.assert_array_equal(view[np.array([5, 0, 5])], crops[[5, 0, 5]][:, :, 2:4, 2:6])
    assert isinstance(crop_array((7, 2, 6, 8), memory_bytes=crops.nbytes), np.ndarray)
    assert isinstance(crop_array((7, 2, 6, 8), memory_bytes=crops.nbytes - 1), CropStore)


def test_streamed_svd_matches_the_exact_one_on_a_slowly_decaying_spectrum():
    """200 crops whose spectrum decays as 1/k (no gap at K = 16): the leading singular values,
    the captured energy and the basis's subspace agree with the exact SVD's."""
    rng = np.random.default_rng(0)
    N, D, K = 200, 3 * 20 * 20, 16
    left = np.linalg.qr(rng.standard_normal((N, N)))[0]
    right = np.linalg.qr(rng.standard_normal((D, N)))[0]
    X = ((left / np.arange(1, N + 1)) @ right.T).astype(np.float32).reshape(N, 3, 20, 20)
    exact = decompose(X, K)
    calls = []
    streamed = streamed_decompose(_store(X, chunk=37), K, progress=lambda *call: calls.append(call))
    assert calls[-1] == ("streamed SVD (chunks read)", 36, 36)  # 6 passes (2 power iterations) × 6 chunks
    np.testing.assert_allclose(streamed.singular_values[:K], exact.singular_values[:K], rtol=2e-3)
    assert streamed.nmse[K] == pytest.approx(exact.nmse[K], rel=1e-3)  # 3.5e-3 with one power iteration
    assert streamed.nmse_per_psf[K] == pytest.approx(exact.nmse_per_psf[K], rel=1e-3)
    overlap = exact.basis.reshape(K, -1) @ streamed.basis.reshape(K, -1).T  # cosines of the principal angles
    cosines = np.linalg.svd(overlap.astype(np.float64), compute_uv=False)
    assert cosines[: K // 2].min() > 0.9999  # the leading half: the same subspace
    assert cosines.min() > 0.99  # the last terms, where 1/k hardly falls, still within 8°
    fitted = np.einsum("nk,kp->np", streamed.coefficients, streamed.basis.reshape(K, -1))
    error = ((fitted - X.reshape(N, -1)) ** 2).sum() / (X**2).sum()
    assert error == pytest.approx(exact.nmse[K], rel=1e-3)  # its coefficients reconstruct the crops as well


def test_streamed_build_gives_the_in_memory_model(v2, tmp_path):
    """A 5×5×3 analytic scan built with its crops in memory and on disk (three positions a chunk):
    the same geometry, focal surface, node errors and images between the nodes."""
    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=19.2)
    axis = np.linspace(-2, 2, 5)
    scan = write_analytic_scan(tmp_path / "scan", analytic, axis, axis, np.linspace(-0.3, 0.3, 3), binning=8)
    options = dict(rank=16, design=v2, rotate=False, warp=False)
    memory = build_model(scan, **options)
    per_position = memory.crops[0].nbytes
    streamed = build_model(scan, **options, memory_bytes=12 * per_position)  # chunks of 3 positions
    assert isinstance(streamed.crops, CropStore) and streamed.crops.chunk == 3
    assert streamed.model.provenance["options"]["svd"] == "streamed (crops on disk)"
    assert memory.model.provenance["options"]["svd"] == "exact (crops in memory)"
    np.testing.assert_array_equal(streamed.crops[:], memory.crops)
    np.testing.assert_allclose(
        streamed.model.focal_surface.coefficients, memory.model.focal_surface.coefficients, atol=1e-9
    )
    a, b = memory.model.provenance["svd"], streamed.model.provenance["svd"]
    assert b["nmse_model"] == pytest.approx(a["nmse_model"], rel=1e-4)
    assert b["patch_px"] == a["patch_px"]
    rng = np.random.default_rng(3)
    for x, y, z in zip(rng.uniform(-1.5, 1.5, 4), rng.uniform(-1.5, 1.5, 4), rng.uniform(-0.2, 0.2, 4), strict=True):
        image, reference = streamed.model.point_image(x, y, z), memory.model.point_image(x, y, z)
        assert ((image - reference) ** 2).sum() / (reference**2).sum() < 1e-6
