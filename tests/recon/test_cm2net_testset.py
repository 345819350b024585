"""CM²Net against FISTA on data it never saw, on a tiny case: issue 15's test set (a) — volumes of
a seed the run never used, made through the weights' own 3D-LSV model at the paper's densities
and diameters, scored for both — and the demo's section 8 (one such measurement, depth-coloured
projections and a metrics table), which says so in one line when the weights are absent."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_net import tiny

from cm2optics.recon.net.data import VALIDATION_SEED_OFFSET
from cm2optics.recon.net.testset import TEST_SEED, net_test_set
from cm2optics.recon.net.train import make_net
from cm2optics.recon.net.weights import save_weights
from cm2optics.synth.config import SynthConfig


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def lsv_weights(lsv_model_path, lsv_model, tmp_path_factory):
    """Untrained tiny weights whose forward model is the shared 8×-binned LSV model (one view pixel
    per 32.9-µm voxel, 7 planes 50 µm apart over 300 µm, 64-px views)."""
    voxel = lsv_model.default_grid.voxel_um[1]
    synth = SynthConfig.scaled(
        4,
        voxel_um=(50.0, voxel, voxel),
        depth_um=300.0,
        view_px=64,
        patch_px=32,
        patches_per_volume=2,
        density_per_mm2=(20.0, 40.0),
    )
    config = tiny(forward_model=str(lsv_model_path), synth=synth, n_planes=synth.grid.shape[0], seed=3)
    net, _ = make_net(config)
    return save_weights(net, config, tmp_path_factory.mktemp("lsv-weights") / "weights")


def test_the_test_set_uses_a_seed_no_training_volume_used_and_scores_net_and_fista(lsv_weights, tmp_path):
    for used in (3, 3 + VALIDATION_SEED_OFFSET):
        with pytest.raises(ValueError, match=f"seed {used} is the"):
            net_test_set(lsv_weights, tmp_path / "refused", seed=used, log=None)
    assert not (tmp_path / "refused").exists()
    summary = net_test_set(lsv_weights, tmp_path / "a", n_volumes=2, fista_iterations=4, workers=0, log=None)
    assert summary["seed"] == TEST_SEED != 3 and summary["n_volumes"] == 2
    assert summary["config"]["density_per_mm2"] == [10.0, 100.0] and summary["config"]["diameter_um"] == [8.0, 20.0]
    manifest = json.loads((tmp_path / "a" / "testset" / "manifest.json").read_text())
    assert manifest["seed"] == TEST_SEED
    assert all(10.0 <= s["density_per_mm2"] <= 100.0 for s in manifest["samples"])
    assert set(summary["runs"]) == {"cm2net", "lsv-fista"}
    assert summary["runs"]["cm2net"]["variant"] == "cm2net"
    for name, run in summary["runs"].items():
        for key in ("recall", "precision", "f1"):
            assert 0.0 <= run[key] <= 1.0, (name, key)
        tp, fp, fn = run["n_tp"], run["n_fp"], run["n_fn"]
        assert tp + fn == summary["n_emitters"], name  # every true emitter is matched or missed
        if tp:
            np.testing.assert_allclose(run["f1"], 2 * tp / (2 * tp + fp + fn), rtol=1e-6)
    assert (tmp_path / "a" / "comparison.md").read_text().count("cm2net") >= 1


def test_the_demo_section_reconstructs_with_the_net_and_fista_and_scores_both(lsv_weights, tmp_path):
    """`cm2 demo` section 8 on the tiny LSV weights: one measurement of the test seed at the
    weights' geometry, the depth-coloured MIPs and a table whose scores are the evaluations'."""
    from cm2optics.recon.net.weights import load_weights
    from cm2optics.reports.document import Report
    from cm2optics.reports.recon import add_net_section

    report = Report("t")
    demo = add_net_section(report, tmp_path, weights=lsv_weights, title="8. CM²Net", fov_mm=1.2, view_px=48)
    assert demo["seed"] == TEST_SEED != load_weights(lsv_weights).config.seed
    assert demo["grid"].shape[0] == 7 and demo["runs"]["net"]["grid"].shape == (7, 48, 48)
    assert len(demo["truth"]) > 0 and (tmp_path / "net" / "mips.png").stat().st_size > 1000
    kinds = [kind for kind, _ in report.blocks]
    assert kinds == ["h2", "p", "figure", "table"]
    header, rows = report.blocks[-1][1]
    assert [r[0] for r in rows] == ["CM²Net", "3D-LSV · FISTA"]
    for row, run in zip(rows, ("net", "fista"), strict=True):
        m = demo["runs"][run]["evaluation"].metrics
        tp, fp, fn = m["n_tp"], m["n_fp"], m["n_fn"]
        assert tp + fn == len(demo["truth"])
        assert row[header.index("F1")] == f"{2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0:.2f}"
    # FISTA through the very model that made the data finds most emitters
    assert demo["runs"]["fista"]["evaluation"].metrics["recall"] >= 0.5


def test_the_demo_section_says_in_one_line_when_the_weights_are_absent(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from cm2optics.cli import app
    from cm2optics.recon.net.weights import shipped_weights
    from cm2optics.reports.document import Report
    from cm2optics.reports.recon import add_net_section

    report = Report("t")
    assert add_net_section(report, tmp_path, weights=tmp_path / "none", title="8. CM²Net") is None
    assert [kind for kind, _ in report.blocks] == ["h2", "p"] and "No trained CM²Net weights" in report.blocks[1][1]
    assert not (tmp_path / "net").exists()
    monkeypatch.chdir(tmp_path)  # found from the package, not from the current directory
    assert shipped_weights() == Path(__file__).resolve().parents[2] / "reconstruction" / "cm2net-cpu"
    refused = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--weights", str(tmp_path / "none")])
    assert refused.exit_code == 2 and "--weights" in refused.output and not (tmp_path / "d").exists()
