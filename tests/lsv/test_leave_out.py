"""`cm2 lsv validate --refit`: leave-one-out in pixels with the build redone without the held-out
nodes, on a tiny analytic scan (whole pixels): the plumbing against closed forms and against
:func:`~cm2optics.lsv.epsf_validate.leave_one_out_pixels` on the same nodes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cm2optics.formats.scan import ScanError, open_scan
from cm2optics.lsv.build import build_model
from cm2optics.lsv.decompose import lenslet_bases
from cm2optics.lsv.epsf_validate import heldout_nodes, leave_one_out_pixels
from cm2optics.lsv.leave_out import held_frames, leave_out_nodes
from cm2optics.lsv.preprocess import extract_crops
from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan


@pytest.fixture(scope="module")
def built(v2, tmp_path_factory):
    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=19.2)
    axis = np.linspace(-3, 3, 4)
    scan = write_analytic_scan(
        tmp_path_factory.mktemp("leave_out") / "scan", analytic, axis, axis, np.linspace(-0.3, 0.3, 3), binning=8
    )
    result = build_model(scan, rank=3, per_lenslet_basis=True, rotate=False, warp=False, design=v2)
    return scan, result.model


def test_refit_of_the_crops_is_leave_one_out_pixels_on_per_lenslet_bases(built):
    scan, model = built
    out = leave_out_nodes(model, scan, n_heldout=3, seed=1)
    assert out["basis"] == "per lenslet, 3 terms each" and out["n_heldout"] == 3 and out["oversample"] == 1
    index = open_scan(scan)
    gi = index.grid_index()
    held = heldout_nodes(gi, 3, 1)
    assert out["held_out_nodes"] == held.tolist()
    patch = model.provenance["options"]["patch_px"]
    crops = extract_crops(index, model.geometry, (patch, patch))
    targets, eps = held_frames(index, model.geometry, held, (patch, patch))
    keep = np.ones(len(gi), bool)
    keep[held] = False
    bases = lenslet_bases(crops[keep], 3)
    assert all(len(b) == 3 for b in bases)
    expected = leave_one_out_pixels(
        crops, gi, index.grid_axes_mm(), targets, eps, 1, held=held, basis=bases, surface=model.focal_surface
    )
    assert out["nmse"] == pytest.approx(expected["interpolated_rank"], rel=1e-9)
    assert out["nmse_full"] == pytest.approx(expected["interpolated_full"], rel=1e-9)
    assert 0 < out["nmse_full"] < 1


def test_refit_of_a_node_model_leaves_the_held_out_nodes_out_of_its_fit_and_its_basis(built):
    scan, model = built
    model = replace(model, provenance={**model.provenance, "node_psfs": {"dense_positions": 0}})
    index = open_scan(scan)
    held = heldout_nodes(index.grid_index(), 3, 0)
    seen = {}

    def node_model(scale):
        def node_psfs(crops, grid_index, axes, geometry, S, pixel_um, *, held_out, progress, memory_bytes):
            seen["held_out"] = np.asarray(held_out).tolist()
            others = np.setdiff1d(np.arange(len(crops)), held_out)
            # a model that knows each held-out node exactly (its own registered crop), basis from the others
            return scale * np.asarray(crops)[held_out], np.asarray(crops)[others], {"dense_positions": len(others)}

        return node_psfs

    with pytest.raises(ValueError, match="needs it"):
        leave_out_nodes(model, scan, n_heldout=3)
    out = leave_out_nodes(model, scan, n_heldout=3, node_psfs=node_model(1.0))
    assert seen["held_out"] == held.tolist()
    # the floor: the node's own crop placed back at its sub-pixel focus (Keys, whole pixels)
    patch = model.provenance["options"]["patch_px"]
    crops = extract_crops(index, model.geometry, (patch, patch))
    targets, eps = held_frames(index, model.geometry, held, (patch, patch))
    floor = leave_one_out_pixels(crops, index.grid_index(), index.grid_axes_mm(), targets, eps, 1, held=held)
    assert out["nmse_full"] == pytest.approx(floor["at_node_full"], rel=1e-9)
    assert out["nmse"] >= 0 and len(out["nmse_per_lenslet"]) == 9 and set(out["nmse_vs_terms"]) == {"3"}
    assert out["nodes_at_or_below_target"] == sum(v <= 0.08 for v in out["nmse_per_node"])
    zero = leave_out_nodes(model, scan, n_heldout=3, node_psfs=node_model(0.0))
    assert zero["nmse_full"] == pytest.approx(1.0) and zero["nmse"] == pytest.approx(1.0)


def test_a_node_model_builds_from_whole_pixel_frames_with_each_focus_phase(v2, built):
    """A scan without epsf.h5: ``node_psfs`` gets the frames' whole-pixel windows and every focus's
    sub-pixel phase, and its fine PSFs make an ePSF model (the aberration model's path for a
    measured scan)."""
    scan, _ = built
    S, seen = 4, {}

    def node_psfs(crops, grid_index, axes, geometry, oversample, pixel_um, *, progress, memory_bytes, phases):
        seen.update(shape=crops.shape, phases=np.asarray(phases), geometry=geometry, oversample=oversample)
        fine = np.kron(np.asarray(crops, np.float64), np.ones((S, S))) / S**2  # any fine PSFs (plumbing)
        return fine.astype(np.float32), fine[::2].astype(np.float32), {"dense_positions": len(fine[::2])}

    result = build_model(scan, rank=3, oversample=S, rotate=False, warp=False, design=v2, node_psfs=node_psfs)
    index = open_scan(scan)
    patch = result.model.provenance["options"]["patch_px"]
    assert seen["shape"] == (len(index), 9, patch, patch) and seen["oversample"] == S
    foci = seen["geometry"].focus(*index.positions_mm.T)
    np.testing.assert_allclose(seen["phases"], foci - np.floor(foci))
    assert len(np.unique(np.round(seen["phases"][:, 4], 3), axis=0)) > 1  # the nodes' phases differ
    assert result.model.oversample == S and result.model.basis.shape[-1] % S == 0
    assert result.model.provenance["node_psfs"]["nmse_nodes_vs_scan"] is None  # no fine crops to compare


@pytest.mark.slow  # ≈ 15 s at load 6 (two ePSF builds)
def test_node_coefficients_from_the_scan_take_the_nodes_from_its_crops_and_the_basis_from_the_model(
    v2, built, monkeypatch
):
    """``scan_node_coefficients``: the basis from the node model's PSFs, the nodes from the scan's
    own fine crops (here the frames' crops, upsampled, stand in for an epsf.h5)."""
    import cm2optics.lsv.build as build

    scan, _ = built
    S = 2

    def fine_crops(index, geometry, patch, oversample, *args, **kwargs):
        crops = extract_crops(index, geometry, (patch, patch))
        return np.kron(crops, np.ones((S, S), np.float32))

    def node_psfs(crops, grid_index, axes, geometry, oversample, pixel_um, *, progress, memory_bytes):
        other = np.roll(crops, 1, axis=-1)  # the "model": every PSF moved by one fine sample
        return other, np.concatenate([crops, other]), {"dense_positions": 2 * len(crops)}

    def node_error(model, index):
        crops = fine_crops(index, model.geometry, model.patch_shape[0], S)
        errors = []
        for n in range(0, len(index), 7):
            p = model.focus_patches(*index.positions_mm[n]).astype(np.float64)
            c = crops[n].astype(np.float64)
            a = (p * c).sum() / (p * p).sum()
            errors.append(((a * p - c) ** 2).sum() / (c * c).sum())
        return float(np.mean(errors))

    index = open_scan(scan)
    monkeypatch.setattr(build, "_scan_crops", fine_crops)
    options = dict(rank=96, oversample=S, rotate=False, warp=False, design=v2, node_psfs=node_psfs, trim=None)
    from_scan = build_model(scan, scan_node_coefficients=True, **options).model
    from_model = build_model(scan, **options).model
    assert from_scan.provenance["node_psfs"]["node_coefficients"].startswith("the scan's own crops")
    assert node_error(from_scan, index) < 1e-6 < 1e-2 < node_error(from_model, index)


def test_node_coefficients_from_a_scan_of_whole_pixel_frames_are_refused_before_the_model_fit(v2, built):
    scan, _ = built

    def node_psfs(*args, **kwargs):
        raise AssertionError("the node model must not run")

    with pytest.raises(ScanError, match="need its fine crops"):
        build_model(scan, rank=3, oversample=2, design=v2, node_psfs=node_psfs, scan_node_coefficients=True)


def test_refit_of_a_node_model_from_whole_pixel_frames_passes_each_frames_phase(v2, built):
    """``--refit`` of a node model built from a scan without epsf.h5: the model is refitted on the
    frames' whole-pixel windows with each focus's sub-pixel phase, its fine predictions placed."""
    scan, model = built
    S = 2
    model = replace(
        model, provenance={**model.provenance, "node_psfs": {"dense_positions": 0}, "epsf": {"oversample": S}}
    )
    index = open_scan(scan)
    seen = {}

    def node_psfs(crops, grid_index, axes, geometry, oversample, pixel_um, *, held_out, progress, memory_bytes, phases):
        seen.update(shape=crops.shape, phases=np.asarray(phases), oversample=oversample)
        fine = np.kron(np.asarray(crops, np.float64), np.ones((S, S)))  # any fine PSFs (plumbing)
        others = np.setdiff1d(np.arange(len(crops)), held_out)
        return fine[held_out], fine[others], {"dense_positions": len(others)}

    out = leave_out_nodes(model, scan, n_heldout=3, node_psfs=node_psfs)
    patch = model.provenance["options"]["patch_px"]
    foci = model.geometry.focus(*index.positions_mm.T)
    assert seen["shape"] == (len(index), 9, patch, patch) and seen["oversample"] == S
    np.testing.assert_allclose(seen["phases"], foci - np.floor(foci))
    assert out["oversample"] == S and 0 <= out["nmse_full"] and len(out["nmse_per_node"]) == 3
