"""CM²Net against FISTA on data it never saw, on a tiny case: issue 15's test set (a) — volumes of
a seed the run never used, made through the weights' own 3D-LSV model at the paper's densities
and diameters, scored for both — and the demo's section 8 (one such measurement, depth-coloured
projections and a metrics table), which says so in one line when the weights are absent."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from tiny_net import tiny

from cm2optics.recon.compare import _model_description, _reusable_testset
from cm2optics.recon.net.data import VALIDATION_SEED_OFFSET
from cm2optics.recon.net.infer import field_view_px
from cm2optics.recon.net.testset import TEST_SEED, net_test_set
from cm2optics.recon.net.train import make_net
from cm2optics.recon.net.weights import load_weights, save_weights
from cm2optics.synth.config import SynthConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")


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
    # fista_iterations=0: the network alone; reuse: its reconstructions of the same set are not remade
    made_at = (tmp_path / "a" / "cm2net" / "run.json").stat().st_mtime_ns
    alone = net_test_set(lsv_weights, tmp_path / "a", n_volumes=2, fista_iterations=0, workers=0, reuse=True, log=None)
    assert set(alone["runs"]) == {"cm2net"} and alone["runs"]["cm2net"]["f1"] == summary["runs"]["cm2net"]["f1"]
    assert (tmp_path / "a" / "cm2net" / "run.json").stat().st_mtime_ns == made_at


@pytest.mark.slow  # a test set and a network run on a Dask worker: ≈ 30 s at load 9, 60 s at load 20
def test_a_whole_field_test_set_spans_the_field_and_the_network_sees_all_of_it(lsv_weights, lsv_model_path, tmp_path):
    """``field_mm``: the volumes fill a disc of that diameter (here 4 mm on the whole 8×-binned
    sensor, the weights trained on ≤ 1.9 mm), the network is given views that hold it (its output
    reaches the field's edge, not the 64-px training views' 2.1 mm), and the model is required."""
    from cm2optics.formats.volume import VolumeGrid
    from cm2optics.synth.dataset import read_sample

    with pytest.raises(ValueError, match="whole sensor"):
        net_test_set(lsv_weights, tmp_path / "refused", field_mm=4.0, log=None)
    out = tmp_path / "w"
    summary = net_test_set(
        lsv_weights, out, n_volumes=1, fista_iterations=0, workers=0, model=lsv_model_path, field_mm=4.0, log=None
    )
    grid = VolumeGrid.from_dict(summary["grid"])
    voxel = grid.voxel_um[1]
    assert summary["config"]["fov_mm"] == [4.0, 4.0] and grid.shape[1] == grid.shape[2] == int(np.ceil(4000 / voxel))
    loaded = load_weights(lsv_weights)
    view_px = field_view_px(4.0, voxel, loaded.planes.max_shift_px)
    assert view_px >= grid.shape[1] + 2 * loaded.planes.max_shift_px > loaded.config.synth.view_px
    run = json.loads((out / "cm2net" / "run.json").read_text())
    assert run["run"]["view_px"] == view_px
    truth = read_sample(next((out / "testset" / "samples").glob("*.h5")))["emitters"]
    radius_mm = np.hypot(truth.x_um, truth.y_um) / 1000.0
    assert 1.7 < radius_mm.max() <= 2.0
    volume = np.load(run["result"]["records"][0]["volume"])
    assert volume.shape == grid.shape
    # 1.8 mm off axis, beyond the training views' 1.05-mm half-width: the untrained net's σ(logit) > 0
    y, x = np.ogrid[: grid.shape[1], : grid.shape[2]]
    ring = np.abs(np.hypot(y - grid.shape[1] / 2, x - grid.shape[2] / 2) * voxel - 1800.0) < 2 * voxel
    assert volume[:, ring].min() > 0.0


@pytest.mark.slow  # two test sets with both runs: ≈ 3 min at load 20
def test_a_model_of_its_own_reconstructs_while_the_weights_model_still_images_set_a(lsv_weights, lsv_model, tmp_path):
    """``model=``: both runs use it (here a rank-3 build of the weights' model, same geometry), the
    measurements are still made through the weights' own model (the same as without it)."""
    from cm2optics.lsv.model import load_model
    from cm2optics.synth.dataset import read_sample

    low = lsv_model.truncated(3).save(tmp_path / "low-rank.lsv.h5")
    runs = {}
    for name, model in (("own", None), ("low", low)):
        runs[name] = net_test_set(
            lsv_weights, tmp_path / name, n_volumes=1, fista_iterations=2, workers=0, model=model, log=None
        )
    assert load_model(tmp_path / "low" / "forward-model.lsv.h5").rank == 3
    assert load_model(tmp_path / "own" / "forward-model.lsv.h5").rank == lsv_model.rank > 3
    measured = [
        read_sample(next((tmp_path / name / "testset" / "samples").glob("*.h5")), verify=False)["measurement"]
        for name in ("own", "low")
    ]
    np.testing.assert_array_equal(measured[0], measured[1])
    assert all(set(r["runs"]) == {"cm2net", "lsv-fista"} for r in runs.values())


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


def test_the_demo_section_says_in_one_line_when_the_weights_are_absent_or_broken(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from cm2optics.cli import app
    from cm2optics.recon.net.weights import shipped_weights
    from cm2optics.reports.document import Report
    from cm2optics.reports.recon import add_net_section

    report = Report("t")
    assert add_net_section(report, tmp_path, weights=tmp_path / "none", title="8. CM²Net") is None
    assert [kind for kind, _ in report.blocks] == ["h2", "p"] and "No trained CM²Net weights" in report.blocks[1][1]
    assert not (tmp_path / "net").exists()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "model.safetensors").write_text("version https://git-lfs.github.com/spec/v1\n")  # an LFS pointer
    report = Report("t")
    assert add_net_section(report, tmp_path, weights=broken, title="8. CM²Net") is None
    assert [kind for kind, _ in report.blocks] == ["h2", "p"] and "cannot be used" in report.blocks[1][1]
    monkeypatch.chdir(tmp_path)  # found from the package, not from the current directory
    assert shipped_weights() == Path(__file__).resolve().parents[2] / "reconstruction" / "cm2net-cpu"
    refused = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "d"), "--weights", str(tmp_path / "none")])
    assert refused.exit_code == 2 and "--weights" in refused.output and not (tmp_path / "d").exists()


# ----------------------------------------------------------------------------- set (b): traced
@pytest.fixture(scope="module")
def analytic_weights(lsv_model, tmp_path_factory):
    """Untrained tiny weights through the analytic CM² V2 model binned 8× (the shipped weights'
    kind of forward model), on a 0.6-mm field so that tracing a test volume takes seconds."""
    voxel = lsv_model.default_grid.voxel_um[1]
    synth = SynthConfig.scaled(
        4,
        voxel_um=(50.0, voxel, voxel),
        depth_um=300.0,
        fov_mm=(0.6, 0.6),
        view_px=32,
        patch_px=16,
        patches_per_volume=2,
    )
    config = tiny(forward_model="analytic:cm2-v2:8", synth=synth, n_planes=synth.grid.shape[0], seed=3)
    net, _ = make_net(config)
    return save_weights(net, config, tmp_path_factory.mktemp("analytic-weights") / "weights")


def test_a_traced_point_lands_on_the_reference_models_chief_rays(analytic_weights, v2):
    """Known answer: an in-focus point on the axis, traced (no LSV model) and cut to the weights'
    sensor window, peaks within 1.5 px of the chief rays of the model the net was trained through."""
    from cm2optics.emission.image import TracedSource
    from cm2optics.formats.emitters import Emitters
    from cm2optics.recon.net.data import forward_imaging

    model = forward_imaging(load_weights(analytic_weights).config).source
    source = TracedSource(v2, model, 8)
    point = Emitters.from_positions_um(np.zeros((1, 3)), np.array([8.0]), np.ones(1))
    frame = source.forward_sparse(point)
    assert frame.shape == tuple(model.sensor_shape)
    for r, c in np.asarray(model.geometry.focus(0.0, 0.0, 0.0)).reshape(-1, 2):
        r0, c0 = int(round(r)), int(round(c))
        local = frame[r0 - 4 : r0 + 5, c0 - 4 : c0 + 5]
        dr, dc = np.unravel_index(np.argmax(local), local.shape)
        assert np.hypot(r0 - 4 + dr - r, c0 - 4 + dc - c) <= 1.5, (r, c)
    with pytest.raises(ValueError, match="per-lenslet"):
        source.forward_sparse(point, per_lenslet=True)
    with pytest.raises(ValueError, match="binning"):
        TracedSource(v2, model, 16).forward_sparse(point)


def test_cm2_net_testset_traced_scores_the_net_and_fista_on_traced_measurements(
    analytic_weights, lsv_weights, v2, tmp_path
):
    """`cm2 net-testset W OUT --traced`: issue 15's set (b) on one traced volume at the paper's
    densities, both runs scored, and reused by a second call with --reuse (the traced set and the
    runs, when the traced design, binning and window are the same); misuse is one line (exit 2)."""
    from typer.testing import CliRunner

    from cm2optics.cli import app
    from cm2optics.emission.image import TracedSource
    from cm2optics.recon.net.data import forward_imaging

    runner = CliRunner()
    out = tmp_path / "b"
    args = ["net-testset", str(analytic_weights), str(out), "--n-volumes", "1", "--fista-iterations", "4"]
    result = runner.invoke(app, [*args, "--traced", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "comparison.json").read_text())
    assert summary["measurements"] == "TracedSource" and summary["seed"] == TEST_SEED
    assert summary["config"]["density_per_mm2"] == [10.0, 100.0] and summary["n_emitters"] > 0
    for name in ("cm2net", "lsv-fista"):
        run = summary["runs"][name]
        assert 0.0 <= run["f1"] <= 1.0 and run["n_tp"] + run["n_fn"] == summary["n_emitters"]
    assert json.loads(result.stdout)["cm2net"]["f1"] == summary["runs"]["cm2net"]["f1"]
    manifest = json.loads((out / "testset" / "manifest.json").read_text())
    traced = manifest["model"]["provenance"]
    top, left, bottom, right = traced["sensor_window"]
    assert (traced["traced"], traced["binning"]) == ("cm2-v2", 8) and bottom > top and right > left
    sample = next((out / "testset" / "samples").glob("*.h5"))
    traced_at, fista_at = sample.stat().st_mtime_ns, (out / "lsv-fista" / "run.json").stat().st_mtime_ns
    again = runner.invoke(app, [*args, "--traced", "--reuse", "--overwrite", "--json"])
    assert again.exit_code == 0, again.output
    assert sample.stat().st_mtime_ns == traced_at and (out / "lsv-fista" / "run.json").stat().st_mtime_ns == fista_at
    assert json.loads(again.stdout) == json.loads(result.stdout)
    # another binning (or design, or window) is another test set; a source without provenance is never reused
    config, reference = SynthConfig.from_dict(summary["config"]), forward_imaging(load_weights(analytic_weights).config)
    for source, reused in (
        (TracedSource(v2, reference.source, 8), True),
        (TracedSource(v2, reference.source, 4), False),
        (SimpleNamespace(provenance={}), False),
    ):
        found = _reusable_testset(
            out / "testset", config, TEST_SEED, 1, _model_description(SimpleNamespace(source=source))
        )
        assert (found is not None) == reused, source
    for extra, weights, message in (
        (["--binning", "8"], analytic_weights, "--traced"),
        (["--traced"], lsv_weights, "--preset and --binning"),
    ):
        failed = runner.invoke(app, ["net-testset", str(weights), str(tmp_path / "x"), *extra])
        assert failed.exit_code == 2 and message in failed.output, failed.output
        assert not (tmp_path / "x").exists()
