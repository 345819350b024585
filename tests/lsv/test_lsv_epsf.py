"""Effective-PSF (oversampled) basis: the ePSF of synthetic foci, sampling at sub-pixel
positions, the dense operator's adjoint and its agreement with exact point images, files, the
whole-pixel estimate and the single-phase fallback."""

from __future__ import annotations

import numpy as np
import pytest
from test_lsv_operators import SENSOR, _inner, synthetic_model

from cm2optics.emission.epsf import epsf_from_subsamples
from cm2optics.lsv.epsf import place_epsf, sampling_matrix
from cm2optics.lsv.epsf_estimate import (
    _Sampler,
    has_dithers,
    local_epsf_crops,
    neighbourhoods,
    phase_coverage,
    phase_spread_px,
)
from cm2optics.lsv.model import LSVModel, load_model

S = 4


def _gaussian_pixel_integral(centre: np.ndarray, shape: tuple[int, int], sigma: float, q: int = 16) -> np.ndarray:
    """A Gaussian focus integrated over whole pixels (sub-sampled q × q), centred at ``centre``."""
    off = (np.arange(q) + 0.5) / q - 0.5
    r = (np.arange(shape[0])[:, None] + off[None, :]).ravel() - centre[0]
    c = (np.arange(shape[1])[:, None] + off[None, :]).ravel() - centre[1]
    fine = np.exp(-(r[:, None] ** 2 + c[None, :] ** 2) / (2 * sigma**2))
    return fine.reshape(shape[0], q, shape[1], q).sum(axis=(1, 3)) / q**2


def _fine_gaussian_epsf(shape: tuple[int, int], sigma: float, centre: tuple[float, float]) -> np.ndarray:
    """ePSF (h·S, w·S) of a Gaussian focus whose chief ray is at patch pixel ``centre``."""
    q = 16
    off = (np.arange(q) + 0.5) / q - 0.5
    h, w = shape
    r = (np.arange(h)[:, None] + off[None, :]).ravel() - centre[0]
    c = (np.arange(w)[:, None] + off[None, :]).ravel() - centre[1]
    fine = np.exp(-(r[:, None] ** 2 + c[None, :] ** 2) / (2 * sigma**2)) / q**2
    return epsf_from_subsamples(fine, q, S)


def test_epsf_of_subsamples_gives_back_the_binned_pixels_at_phase_zero():
    rng = np.random.default_rng(0)
    q = 8
    fine = rng.random((5 * q, 6 * q))
    pixels = fine.reshape(5, q, 6, q).sum(axis=(1, 3))
    epsf = epsf_from_subsamples(fine, q, S)
    assert epsf.shape == (5 * S, 6 * S)
    np.testing.assert_allclose(epsf[::S, ::S], pixels, rtol=1e-12)
    # a quarter-pixel step: the pixel integral shifted by 2 sub-samples
    shifted = np.pad(fine, ((0, 0), (0, q)))[:, 2 : 2 + 6 * q].reshape(5, q, 6, q).sum(axis=(1, 3))
    np.testing.assert_allclose(epsf[::S, 1::S], shifted, rtol=1e-12)
    with pytest.raises(ValueError, match="oversample"):
        epsf_from_subsamples(fine, q, 3)


@pytest.mark.parametrize("eps", [(0.0, 0.0), (0.25, 0.5), (0.4, 0.9), (0.13, 0.71)])
def test_a_sampled_epsf_is_the_pixel_integral_at_any_sub_pixel_position(eps):
    """A 0.45-px Gaussian (narrower than a pixel): the whole-pixel Keys shift misses by ~10 %,
    the ePSF sampled at the exact position by < 1 %."""
    h, w, sigma = 10, 10, 0.45
    epsf = _fine_gaussian_epsf((h, w), sigma, (h // 2, w // 2))
    placed = place_epsf(epsf, eps, S)  # pixel (r, c) ↔ patch coordinate (r − 1 − eps)
    truth = _gaussian_pixel_integral(np.array([h // 2 + 1 + eps[0], w // 2 + 1 + eps[1]]), (h + 3, w + 3), sigma)
    error = np.linalg.norm(placed - truth) / np.linalg.norm(truth)
    assert error < 0.01
    from cm2optics.lsv.sparse import _shift_patch

    whole = _shift_patch(epsf[::S, ::S], eps)
    if eps != (0.0, 0.0):
        assert np.linalg.norm(whole - truth) / np.linalg.norm(truth) > 5 * error


def test_sampling_matrix_interpolates_exactly_on_the_fine_grid():
    M = sampling_matrix(np.array([0.0, 3.0, 7.0, -1.0]), 8)
    np.testing.assert_allclose(M[:3], np.eye(8)[[0, 3, 7]], atol=1e-12)
    assert np.all(M[3] == 0)


def epsf_model(kind: str = "diag", seed: int = 0) -> LSVModel:
    """The synthetic model of test_lsv_operators with a smooth 4× oversampled basis."""
    from dataclasses import replace

    model = synthetic_model(kind, seed=seed)
    K, J, h, w = model.basis.shape
    h, w = 10, 12
    rng = np.random.default_rng(seed)
    basis = np.zeros((K, J, h * S, w * S), np.float32)
    for k in range(K):
        for j in range(J):
            centre = (h // 2 + rng.normal(0, 0.7), w // 2 + rng.normal(0, 0.7))
            basis[k, j] = _fine_gaussian_epsf((h, w), 0.6 + 0.5 * rng.random(), centre) * rng.normal()
    return replace(model, basis=basis, oversample=S)


def test_epsf_model_patch_shape_and_file_round_trip(tmp_path):
    model = epsf_model()
    assert model.patch_shape == (10, 12) and model.basis.shape[2:] == (40, 48)
    path = model.save(tmp_path / "m.h5")
    again = load_model(path)
    assert again.oversample == S
    np.testing.assert_array_equal(again.basis, model.basis)


@pytest.mark.parametrize("kind", ["diag", "general"])
def test_epsf_operator_adjoint_identity(kind):
    model = epsf_model(kind)
    op = model.operator()
    rng = np.random.default_rng(1)
    x = rng.random(op.grid.shape).astype(np.float32)
    y = rng.normal(size=SENSOR).astype(np.float32)
    Ax, ATy = op.forward(x), op.adjoint(y)
    assert Ax.shape == SENSOR and ATy.shape == op.grid.shape
    lhs, rhs = _inner(Ax, y), _inner(x, ATy)
    assert abs(lhs - rhs) <= 1e-5 * max(abs(lhs), abs(rhs))
    per_lenslet = op.forward(x, per_lenslet=True)
    np.testing.assert_allclose(per_lenslet.sum(0), Ax, rtol=1e-4, atol=1e-5 * np.abs(Ax).max())


def test_a_single_voxel_of_the_epsf_operator_images_like_the_exact_point_image():
    """Dense (fine-grid operator, sampled at the pixel centres) and sparse (ePSF sampled at the
    exact focus) agree for a voxel between the calibration nodes."""
    model = epsf_model()
    grid = model.default_grid
    nz, ny, nx = grid.shape
    volume = np.zeros(grid.shape, np.float32)
    iz, iy, ix = nz // 2 + 1, ny // 2 + 3, nx // 2 - 2
    volume[iz, iy, ix] = 1.0
    dense = model.forward(volume)
    z, y, x = (grid.axis_mm(a)[i] for a, i in ((0, iz), (1, iy), (2, ix)))
    exact = model.point_image(x, y, z)
    assert np.linalg.norm(dense - exact) <= 0.02 * np.linalg.norm(exact)


def test_sampler_adjoint_identity():
    rng = np.random.default_rng(2)
    eps = rng.random((5, 2))
    sampler = _Sampler(eps, 6, 7, S)
    import torch

    fine = torch.as_tensor(rng.normal(size=(5, 24, 28)), dtype=torch.float32)
    image = torch.as_tensor(rng.normal(size=(5, 6, 7)), dtype=torch.float32)
    lhs = float((sampler.forward(fine, slice(0, 5)) * image).sum())
    rhs = float((fine * sampler.adjoint(image, slice(0, 5))).sum())
    assert abs(lhs - rhs) < 1e-4 * abs(lhs)


def test_phase_coverage_flags_a_scan_of_one_phase():
    model = synthetic_model()
    geometry = model.geometry
    xs, ys, zs = model.axes
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
    assert not phase_coverage(geometry, grid, S)["single_phase"]
    # positions whose foci all move by whole pixels: one phase
    from dataclasses import replace

    from cm2optics.lsv.preprocess import Geometry

    flat = Geometry(np.array([[10.0, 12.0]]), np.array([[[0.0, -20.0], [-20.0, 0.0]]]), np.zeros((1, 4, 2)), 2, 2)
    one = np.array([[x, y, 0.0] for x in (-0.1, 0.0, 0.1) for y in (-0.05, 0.1)])
    coverage = phase_coverage(replace(flat), one, S)
    assert coverage["single_phase"] and coverage["min_bins_visited"] == pytest.approx(1 / S**2, abs=1e-3)


def test_neighbourhoods_pool_the_sub_pixel_dithers_of_a_node_at_its_depth():
    # two nodes 24 px apart, each dithered by ½ px in x and y, at two depths; two lenslets
    base = np.array([[[10.0, 10.0], [10.0, 40.0]], [[10.0, 34.0], [10.0, 64.0]]])  # (node, lenslet, 2)
    dither = np.array([[0.0, 0.0], [0.0, 0.5], [0.5, 0.0], [0.5, 0.5]])
    foci = np.stack([b + d for b in base for d in dither] * 2)  # (16, 2, 2)
    depth = np.repeat([0, 1], 8)
    groups = neighbourhoods(foci, depth)
    assert sorted(groups[0]) == [0, 1, 2, 3] and groups[0][0] == 0
    assert sorted(groups[5]) == [4, 5, 6, 7] and groups[5][0] == 5
    assert sorted(groups[9]) == [8, 9, 10, 11]  # the same foci at the other depth: not pooled
    assert [list(g) for g in neighbourhoods(foci, depth, within_px=0.0)] == [[n] for n in range(16)]
    assert has_dithers(foci, depth) and not has_dithers(foci[::4], depth[::4])  # one frame per node: none


def test_local_epsf_of_dithered_frames_is_the_pixel_integrated_focus():
    """A focus narrower than a pixel (σ = 0.6 px), seen whole-pixel at 9 random sub-pixel
    dithers of one node: their pooled estimate is its ePSF to 3 %; one frame alone is not (15 %)."""
    rng = np.random.default_rng(0)
    h, sigma = 12, 0.6
    eps = rng.random((9, 1, 2))
    foci = 20.0 + eps  # (9 frames, 1 lenslet, 2), all within 1.5 px
    # pixel r of a window is at patch coordinate r − eps: the chief ray on window pixel h//2 + eps
    windows = np.stack([_gaussian_pixel_integral(h // 2 + e[0], (h, h), sigma) for e in eps])[:, None]
    truth = _fine_gaussian_epsf((h, h), sigma, (h // 2, h // 2))
    depth = np.zeros(9, int)
    pooled, report = local_epsf_crops(windows.astype(np.float32), foci, depth, S, within_px=1.5)
    alone, alone_report = local_epsf_crops(windows.astype(np.float32), foci, depth, S, within_px=0.0)
    assert np.linalg.norm(pooled[0, 0] - truth) < 0.03 * np.linalg.norm(truth)
    assert np.linalg.norm(alone[0, 0] - truth) > 0.1 * np.linalg.norm(truth)
    assert report["nodes_per_neighbourhood"]["min"] == 9 and report["phase_bins_per_neighbourhood"]["of"] == S * S
    assert report["nodes_of_one_phase"] == 0 and alone_report["nodes_of_one_phase"] == 9


def test_phase_spread_tells_a_sub_pixel_dither_from_none_and_from_a_whole_pixel_one():
    node = np.array([[[0.3, 0.7], [0.9, 0.1]]])  # (1 frame, 2 lenslets, 2) phases, px
    assert phase_spread_px(node) == 0.0  # alone
    whole = np.concatenate([node, node])  # dithered by whole pixels: the same phases
    assert phase_spread_px(whole) == pytest.approx(0.0, abs=1e-12)
    half = np.concatenate([node, (node + [0.5, 0.0]) % 1.0])  # ½ px in x on both lenslets
    assert phase_spread_px(half) == pytest.approx(0.5)
    one_lenslet = np.concatenate([node, node + [[[0.0, 0.25], [0.0, 0.0]]]])  # only lenslet 0 moves
    assert phase_spread_px(one_lenslet) == pytest.approx(0.0, abs=1e-12)  # the least dithered lenslet
    near_wrap = np.concatenate([node, (node + [0.0, 0.45]) % 1.0])  # 0.7 + 0.45 wraps to 0.15
    assert phase_spread_px(near_wrap) == pytest.approx(0.45)


@pytest.fixture(scope="module")
def small_analytic_scan(v2, tmp_path_factory):
    from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan

    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=12.0)
    axis = np.linspace(-2, 2, 5)
    folder = tmp_path_factory.mktemp("epsf") / "scan"
    return write_analytic_scan(folder, analytic, axis, axis, np.array([-0.2, 0.0, 0.2]), binning=8, noise=False)


def test_build_estimates_an_epsf_basis_from_whole_pixel_frames(small_analytic_scan, v2):
    from cm2optics.lsv.build import build_model

    result = build_model(
        small_analytic_scan, rank=8, design=v2, oversample=2, estimate_options={"iterations": 2, "cg_steps": 5}
    )
    model = result.model
    assert model.oversample == 2 and model.basis.shape[2:] == tuple(2 * s for s in model.patch_shape)
    epsf = model.provenance["epsf"]
    assert epsf["source"] == "estimated from the whole-pixel frames"  # no dithers: the joint fit
    assert 0 < epsf["phase_coverage"]["min_bins_visited"] <= 1
    misfit = epsf["estimate"]["pixel_misfit_nmse_per_iteration"]
    assert misfit[-1] < misfit[0]
    # an in-focus unit source on the axis still images to a total of 1
    assert model.point_image(0.0, 0.0, 0.0).sum() == pytest.approx(1.0, rel=0.05)


def test_build_pools_each_nodes_sub_pixel_dithers(v2, tmp_path):
    from cm2optics.lsv.build import build_model
    from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan

    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=12.0)
    axis = np.array([-1.0, -0.99, 0.0, 0.01, 1.0, 1.01])  # nodes 1 mm apart, dithered by 10 µm (≈ ⅓ px)
    scan = write_analytic_scan(
        tmp_path / "scan", analytic, axis, axis, np.array([-0.2, 0.0, 0.2]), binning=8, noise=False
    )
    model = build_model(scan, rank=8, design=v2, oversample=2, estimate_options={"cg_steps": 10}).model
    epsf = model.provenance["epsf"]
    assert epsf["source"].endswith("each node and its sub-pixel dithers")
    assert epsf["estimate"]["nodes_per_neighbourhood"] == {"min": 4, "median": 4.0}
    assert model.basis.shape[2:] == tuple(2 * s for s in model.patch_shape)
    assert model.point_image(0.0, 0.0, 0.0).sum() == pytest.approx(1.0, rel=0.05)


def test_a_scan_dithered_at_some_nodes_only_warns_of_the_undithered_ones(v2, tmp_path):
    from cm2optics.lsv.build import build_model
    from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan

    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=12.0)
    axis = np.array([-1.0, -0.99, 0.0, 1.0])  # only the node at -1 mm is dithered (10 µm ≈ ⅓ px)
    scan = write_analytic_scan(tmp_path / "scan", analytic, axis, axis, np.array([-0.1, 0.1]), binning=8, noise=False)
    with pytest.warns(UserWarning, match="8 of 32 nodes have no sub-pixel dither"):
        model = build_model(scan, rank=4, design=v2, oversample=2, estimate_options={"cg_steps": 4}).model
    estimate = model.provenance["epsf"]["estimate"]
    # per depth: (0, 0), (0, 1), (1, 0) and (1, 1) mm have no frame within 1 px at another phase
    assert estimate["nodes_of_one_phase"] == 8
    assert "dither every node" in model.provenance["epsf"]["warning"]


def test_a_scan_of_one_sub_pixel_phase_falls_back_to_whole_pixels(small_analytic_scan, v2, monkeypatch):
    import cm2optics.lsv.epsf_estimate as estimate
    from cm2optics.lsv.build import build_model

    real = estimate.phase_coverage
    monkeypatch.setattr(estimate, "phase_coverage", lambda *a: {**real(*a), "single_phase": True})
    with pytest.warns(UserWarning, match="same sub-pixel phase"):
        result = build_model(small_analytic_scan, rank=4, design=v2, oversample=4)
    assert result.model.oversample == 1
    epsf = result.model.provenance["epsf"]
    assert epsf["oversample"] == 1 and epsf["requested_oversample"] == 4 and "whole pixels" in epsf["fallback"]


def test_a_coarser_operator_sampling_stays_adjoint_and_close():
    from cm2optics.lsv.epsf import EPSFOperator

    model = epsf_model()
    grid = model.default_grid
    op = EPSFOperator(model, grid, sampling=2)
    rng = np.random.default_rng(3)
    x = rng.random(grid.shape).astype(np.float32)
    y = rng.normal(size=SENSOR).astype(np.float32)
    lhs, rhs = _inner(op.forward(x), y), _inner(x, op.adjoint(y))
    assert abs(lhs - rhs) <= 1e-5 * max(abs(lhs), abs(rhs))
    full = model.forward(x)
    assert np.linalg.norm(op.forward(x) - full) <= 0.05 * np.linalg.norm(full)


def test_build_table_rows_say_where_the_epsf_came_from_and_how_it_was_pooled():
    from cm2optics.cli.lsv import _epsf_rows

    coverage = {"oversample": 4, "min_bins_visited": 1.0, "min_nodes_per_bin": 16, "single_phase": False}
    estimate = {
        "nodes_per_neighbourhood": {"min": 4, "median": 4.0},
        "phase_bins_per_neighbourhood": {"min": 4, "median": 4.0, "of": 16},
        "nodes_of_one_phase": 0,
    }
    source = "estimated from the whole-pixel frames of each node and its sub-pixel dithers"
    rows = dict(_epsf_rows({"oversample": 4, "phase_coverage": coverage, "estimate": estimate, "source": source}))
    assert rows["ePSF oversample"] == f"4 ({source})"
    assert rows["sub-pixel phase bins visited (worst lenslet)"] == "100%"
    assert rows["frames pooled per node (dithers)"] == "median 4, min 4; phase bins ≥ 4 of 16; 0 nodes of one phase"
    fallback = dict(_epsf_rows({"oversample": 1, "requested_oversample": 4, "fallback": "one phase: whole pixels"}))
    assert fallback == {"ePSF oversample": "1 (one phase: whole pixels)"}
    assert _epsf_rows({}) == []


def test_the_turn_check_predicts_a_dithered_node_from_the_nodes_beyond_its_dithers():
    """Focus width σ = 1 + x² px (x mm) on a grid dithered by 10 µm (½ px at 50 px/mm): a node's
    grid neighbour is its own dither, so the plain check predicts every node near exactly; on the
    nodes alone (:func:`undithered_axis`) the one interior node, x = y = 0, is predicted from x = ±1
    (σ = 2) and y = ±1 (σ = 1): NMSE ½ · ‖g₂ − g₁‖²/‖g₁‖²."""
    from cm2optics.lsv.epsf_validate import turn_check, undithered_axis

    values = np.array([-1.0, -0.99, 0.0, 0.01, 1.0, 1.01])
    assert undithered_axis(values, 50.0, 1.0).tolist() == [0, 2, 4]
    assert undithered_axis(values, 200.0, 1.0).tolist() == list(range(6))  # 2 px apart: all nodes
    r = np.arange(16) - 7.5
    blob = lambda sigma: np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))  # noqa: E731
    zs = np.array([-0.1, 0.0, 0.1])
    grid = np.array([(ix, iy, iz) for iz in range(3) for iy in range(6) for ix in range(6)])
    crops = np.stack([blob(1 + values[ix] ** 2)[None] for ix, _, _ in grid])  # (N, 1 lenslet, 16, 16)
    axes = (values, values, zs)
    plain = turn_check(crops, grid, axes, None, None, n_heldout=24)
    nodes = (undithered_axis(values, 50.0, 1.0),) * 2
    check = turn_check(crops, grid, axes, None, None, n_heldout=24, lateral=nodes)
    expected = 0.5 * ((blob(2.0) - blob(1.0)) ** 2).sum() / (blob(1.0) ** 2).sum()
    assert check["n_heldout"] == 1 and check["nmse_fixed_orientation"] == pytest.approx(expected, rel=1e-9)
    assert plain["nmse_fixed_orientation"] < 0.2 * expected  # fooled: the dithers predict each other
