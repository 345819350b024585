"""Model-based baselines: operators (adjoint, orientation, the LSI model of an LSV model),
regularisers, step size, every solver recovering a few emitters through a tiny analytic
operator, the stopping rule, the memory guard and `cm2 reconstruct`."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.lsi import DepthwiseConvOperator, lsi_from_model
from cm2optics.lsv.toy import gaussian_lsi_operator
from cm2optics.metrics import evaluate_volume
from cm2optics.recon.operators import load_operator
from cm2optics.recon.reconstruct import ReconOptions, memory_estimate, reconstruct
from cm2optics.recon.regularizers import TV
from cm2optics.recon.solvers import Stopping, fista, power_iteration

GRID = VolumeGrid((9, 30, 30), (20.0, 4.0, 4.0))


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Small tensors: one intra-op thread is faster, and far faster on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def op() -> DepthwiseConvOperator:
    return gaussian_lsi_operator(GRID, (110, 110), defocus_px_per_um=0.01, shear_per_um=4e-4)


@pytest.fixture(scope="module")
def scene(op):
    """Four emitters on voxel centres, their noise-free measurement."""
    z, y, x = (GRID.axis_um(a) for a in range(3))
    idx = [(2, 8, 9), (4, 20, 21), (6, 10, 22), (7, 22, 7)]
    truth = Emitters(
        [x[i[2]] for i in idx], [y[i[1]] for i in idx], [z[i[0]] for i in idx], [6.0] * 4, [1.0, 0.8, 1.2, 1.0]
    )
    volume = np.zeros(GRID.shape, np.float32)
    for (a, b, c), v in zip(idx, truth.intensity, strict=True):
        volume[a, b, c] = v
    return truth, volume, op.forward(volume)


def test_adjoint_identity_and_orientation(op):
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.random(GRID.shape), dtype=torch.float32)
    y = torch.as_tensor(rng.random(op.sensor_shape), dtype=torch.float32)
    lhs, rhs = float((op.forward(x) * y).sum()), float((x * op.adjoint(y)).sum())
    assert lhs == pytest.approx(rhs, rel=1e-5)
    # a source moved +x lands −x (the lenslets invert), +y lands −y
    a = np.zeros(GRID.shape, np.float32)
    b = a.copy()
    a[4, 15, 15] = 1
    b[4, 18, 15 + 4] = 1
    from scipy import ndimage

    ca, cb = ndimage.center_of_mass(op.forward(a)), ndimage.center_of_mass(op.forward(b))
    assert (cb[0] - ca[0], cb[1] - ca[1]) == pytest.approx((-3.0, -4.0), abs=1e-3)
    # per-lenslet images add up to the image; each carries 1/9 of the light
    parts = op.forward(a, per_lenslet=True)
    assert parts.shape == (9,) + op.sensor_shape
    np.testing.assert_allclose(parts.sum(0), op.forward(a), atol=1e-6)
    assert parts.sum((1, 2)) == pytest.approx(np.full(9, 1 / 9), rel=1e-4)


def test_batched_operators_and_file_round_trip(op, tmp_path):
    x = torch.rand((2,) + GRID.shape)
    np.testing.assert_allclose(op.forward(x)[1], op.forward(x[1]), atol=1e-6)
    path = op.save(tmp_path / "stack.h5")
    again = load_operator(path)
    np.testing.assert_allclose(again.forward(x[0]), op.forward(x[0]), atol=1e-6)
    np.testing.assert_allclose(again.chief_rays_px(), op.chief_rays_px())
    with pytest.raises(ValueError, match="own grid"):
        load_operator(path, VolumeGrid((3, 3, 3), (1.0, 1.0, 1.0)))


def test_power_iteration_matches_the_dense_matrix():
    grid = VolumeGrid((2, 6, 6), (20.0, 4.0, 4.0))
    small = gaussian_lsi_operator(grid, (30, 30), pitch_px=9)
    columns = []
    for k in range(int(np.prod(grid.shape))):
        e = np.zeros(grid.shape, np.float32)
        e.flat[k] = 1
        columns.append(small.forward(e).ravel())
    dense = np.stack(columns, axis=1).astype(np.float64)
    exact = np.linalg.norm(dense, 2) ** 2
    assert power_iteration(small, iterations=60) == pytest.approx(1.02 * exact, rel=1e-3)


def test_tv_gradient_adjoint_and_prox():
    tv = TV((0.5, 1.0, 1.0), iterations=30)
    x = torch.rand(GRID.shape)
    p = torch.rand((3,) + GRID.shape)
    assert float((tv.grad(x) * p).sum()) == pytest.approx(float((x * tv.grad_adjoint(p)).sum()), rel=1e-5)
    noisy = torch.zeros(GRID.shape)
    noisy[3:6, 10:20, 10:20] = 1
    noisy += 0.2 * torch.randn(GRID.shape, generator=torch.Generator().manual_seed(0))
    smooth = tv.prox(noisy, 0.2)
    assert smooth.min() >= 0
    assert tv.value(smooth) < 0.5 * tv.value(noisy)
    assert torch.equal(tv.prox(noisy, 0.0), torch.clamp(noisy, min=0))


@pytest.mark.parametrize(
    ("method", "extra"),
    [("fista", {}), ("fista", {"tv": 0.002}), ("admm", {}), ("admm", {"tv": 0.002}), ("rl", {"l1": 0.0})],
    ids=["fista", "fista-tv", "admm-lsi", "admm-lsi-tv", "rl"],
)
def test_every_method_recovers_a_few_emitters(op, scene, method, extra):
    truth, volume, image = scene
    options = ReconOptions(method=method, max_iter=150, background="none", **({"l1": 0.01} | extra))
    recon, record = reconstruct(image, op, options)
    assert recon.shape == GRID.shape and recon.min() >= 0
    result = evaluate_volume(recon, GRID, truth, threshold=0.3 * float(recon.max()))
    m = result.metrics
    assert (m["recall"], m["precision"]) == (1.0, 1.0), m
    assert m["rmse_lateral_um"] <= 2.0 and m["rmse_axial_um"] <= 10.0
    assert record["iterations"] <= 150 and record["variant"].startswith(method)


def test_generic_admm_with_an_operator_that_is_not_convolutional(op, scene):
    class Wrapped:  # hides the convolution structure: ADMM falls back to its CG x-update
        grid, sensor_shape = op.grid, op.sensor_shape

        def forward(self, v):
            return op.forward(v)

        def adjoint(self, y):
            return op.adjoint(y)

    truth, _, image = scene
    recon, record = reconstruct(image, Wrapped(), ReconOptions(method="admm", l1=0.01, max_iter=80, background="none"))
    assert record["variant"] == "admm (CG x-update)"
    m = evaluate_volume(recon, GRID, truth, threshold=0.3 * float(recon.max())).metrics
    assert (m["recall"], m["precision"]) == (1.0, 1.0)


def test_stopping_rule(op, scene):
    _, _, image = scene
    loose = fista(op, torch.as_tensor(image), l1=0.01, stopping=Stopping(max_iter=200, tol=0.05, patience=2))
    assert loose.converged and loose.iterations < 200
    assert all(c < 0.05 for c in loose.history["rel_change"][-2:])
    capped = fista(op, torch.as_tensor(image), l1=0.01, stopping=Stopping(max_iter=7, tol=0.0))
    assert not capped.converged and capped.iterations == 7
    with pytest.raises(ValueError, match="patience"):
        Stopping(patience=0)


def test_background_and_scale_are_undone(op, scene):
    truth, _, image = scene
    recon_a, rec_a = reconstruct(image, op, ReconOptions(l1=0.01, max_iter=60, background="none"))
    recon_b, rec_b = reconstruct(3.0 * image + 0.05, op, ReconOptions(l1=0.01, max_iter=60, background=0.05))
    np.testing.assert_allclose(recon_b, 3.0 * recon_a, rtol=1e-3, atol=1e-4 * float(recon_b.max()))


def test_memory_guard_and_bad_input(op, scene):
    _, _, image = scene
    estimate = memory_estimate(op, ReconOptions(method="admm", tv=0.1))
    assert estimate["volume_copies"] > memory_estimate(op, ReconOptions(method="admm"))["volume_copies"]
    with pytest.raises(ValueError, match="max-memory-gib"):
        reconstruct(image, op, ReconOptions(max_memory_gib=1e-6))
    with pytest.raises(ValueError, match="sensor"):
        reconstruct(image[:-1], op)
    with pytest.raises(ValueError, match="NaN"):
        reconstruct(np.full(op.sensor_shape, np.nan), op)
    with pytest.raises(ValueError, match="method"):
        ReconOptions(method="magic")


# ----------------------------------------------------------------------------- CLI


def _app():
    from cm2optics.cli.evaluate import evaluate_command
    from cm2optics.cli.reconstruct import reconstruct_command

    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """test app"""

    app.command("reconstruct")(reconstruct_command)
    app.command("evaluate")(evaluate_command)
    return app


def test_cli_reconstruct_then_evaluate(op, scene, tmp_path):
    import tifffile

    from cm2optics.formats.emitters import write_emitters
    from cm2optics.formats.volume import read_volume

    truth, _, image = scene
    model = op.save(tmp_path / "model.h5")
    tifffile.imwrite(tmp_path / "meas.tif", (image / image.max() * 60000 + 100).astype(np.uint16))
    write_emitters(tmp_path / "truth.csv", truth)
    runner = CliRunner()
    result = runner.invoke(
        _app(),
        [
            "reconstruct",
            str(tmp_path / "meas.tif"),
            "--model",
            str(model),
            "--method",
            "fista",
            "--out",
            str(tmp_path / "vol.tif"),
            "--dark-level",
            "100",
            "--background",
            "none",
            "--device",
            "cpu",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert record["method"] == "fista" and record["iterations"] >= 1 and "memory_estimate" in record
    assert record["device"] == "cpu"
    volume, grid = read_volume(tmp_path / "vol.tif")
    assert grid.shape == GRID.shape and grid.voxel_um == pytest.approx(GRID.voxel_um, rel=1e-5)
    assert json.loads((tmp_path / "vol.json").read_text())["volume"] == str(tmp_path / "vol.tif")
    result = runner.invoke(_app(), ["evaluate", str(tmp_path / "vol.tif"), str(tmp_path / "truth.csv"), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["recall"] == 1.0


def _one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    return lines[0]


def test_cli_reconstruct_errors_are_one_line(op, tmp_path):
    import tifffile

    model = op.save(tmp_path / "model.h5")
    tifffile.imwrite(tmp_path / "small.tif", np.ones((10, 10), np.uint16))
    runner = CliRunner()
    args = ["reconstruct", str(tmp_path / "small.tif"), "--model", str(model), "--out", str(tmp_path / "v.tif")]
    assert "sensor" in _one_line_error(runner.invoke(_app(), args))
    assert "method" in _one_line_error(runner.invoke(_app(), args + ["--method", "sgd"]))
    assert "no such measurement" in _one_line_error(
        runner.invoke(
            _app(), ["reconstruct", str(tmp_path / "none.tif"), "--model", str(model), "--out", str(tmp_path / "v.tif")]
        )
    )
    assert "no such model" in _one_line_error(
        runner.invoke(
            _app(),
            [
                "reconstruct",
                str(tmp_path / "small.tif"),
                "--model",
                str(tmp_path / "m.h5"),
                "--out",
                str(tmp_path / "v.tif"),
            ],
        )
    )
    assert ".tif or .npy" in _one_line_error(runner.invoke(_app(), args[:-1] + [str(tmp_path / "v.png")]))
    assert "cpu or cuda" in _one_line_error(runner.invoke(_app(), args + ["--device", "gpu"]))
    assert "cpu or cuda" in _one_line_error(runner.invoke(_app(), args + ["--device", "mps"]))
    assert "CUDA device" in _one_line_error(runner.invoke(_app(), args + ["--device", "cuda:99"]))
    assert not (tmp_path / "v.tif").exists()


# ----------------------------------------------------------------------------- LSV → LSI


def test_lsi_of_an_lsv_model_is_exact_on_the_axis_and_wrong_off_it(lsv_model):
    model = lsv_model
    grid = VolumeGrid((5, 61, 61), (200.0,) + model.default_grid.voxel_um[1:])
    lsi = lsi_from_model(model, grid)
    lsv = model.operator(grid)
    centre = np.zeros(grid.shape, np.float32)
    centre[4, 30, 30] = 1  # on the axis, defocused (+400 µm)
    a, b = lsi.forward(centre), np.asarray(lsv.forward(centre))
    assert np.linalg.norm(a - b) / np.linalg.norm(b) < 0.1
    edge = np.zeros(grid.shape, np.float32)
    edge[4, 30, 58] = 1  # 0.93 mm off the axis, same depth: the LSI model misses the field's change
    a, b = lsi.forward(edge), np.asarray(lsv.forward(edge))
    assert np.linalg.norm(a - b) / np.linalg.norm(b) > 0.2
    x = torch.rand(grid.shape)
    y = torch.rand(model.sensor_shape)
    assert float((lsi.forward(x) * y).sum()) == pytest.approx(float((x * lsi.adjoint(y)).sum()), rel=1e-4)
    with pytest.raises(ValueError, match="one voxel per sensor pixel"):
        lsi_from_model(model, VolumeGrid((5, 31, 31), (200.0, 2 * grid.voxel_um[1], 2 * grid.voxel_um[2])))


def test_fft_lsi_operator_agrees_with_the_lsv_packages_lsi_model(lsv_model):
    """The closed-form ADMM's FFT operator: exact on the voxel column nearest the axis (odd and
    even grids), and where cm2optics.lsv.lsi's LSI model puts the light elsewhere."""
    from scipy import ndimage

    from cm2optics.lsv.lsi import lsi_model

    for n in (61, 60):  # the axis on a voxel, or between two
        grid = VolumeGrid((9, n, n), (100.0,) + lsv_model.default_grid.voxel_um[1:])
        ours, lsv, theirs = (
            lsi_from_model(lsv_model, grid),
            lsv_model.operator(grid),
            lsi_model(lsv_model).operator(grid),
        )
        for position in [(4, n // 2, n // 2), (8, n // 2, n // 2), (8, 30, 55), (0, 5, 55)]:
            volume = np.zeros(grid.shape, np.float32)
            volume[position] = 1
            a = ours.forward(volume)
            if position[1:] == (n // 2, n // 2):
                b = np.asarray(lsv.forward(volume))  # exact point image against the operator's sampling
                assert np.linalg.norm(a - b) / np.linalg.norm(b) < 0.06, (n, position)
            b = np.asarray(theirs.forward(volume))
            ca, cb = ndimage.center_of_mass(np.maximum(a, 0)), ndimage.center_of_mass(np.maximum(b, 0))
            assert np.hypot(ca[0] - cb[0], ca[1] - cb[1]) < 0.6, (n, position)


@pytest.mark.slow
def test_lsv_against_lsi_comparison_end_to_end(lsv_model, tmp_path):
    """The comparison pipeline on two small volumes (the real run: cm2 compare-baselines)."""
    from cm2optics.recon.compare import compare_baselines, scaled_test_config

    path = lsv_model.save(tmp_path / "model.h5")
    config = scaled_test_config(lsv_model, 4, density_per_mm2=(20.0, 40.0))
    runs = {
        "lsv-fista": {"forward": "lsv", "method": "fista", "l1": 0.02, "max_iter": 8},
        "lsi-admm": {"forward": "lsi", "method": "admm", "l1": 0.02, "max_iter": 4},
    }
    summary = compare_baselines(path, tmp_path / "cmp", n_volumes=2, config=config, runs=runs, log=None)
    for name in runs:
        entry = summary["runs"][name]
        for key in ("recall", "precision", "f1", "jaccard", "seconds_per_volume", "peak_rss_gib", "threshold"):
            assert entry[key] is not None, key
        assert (tmp_path / "cmp" / f"maps_{name}.png").is_file()
    assert (tmp_path / "cmp" / "comparison.md").read_text().count("|") > 20
    assert json.loads((tmp_path / "cmp" / "comparison.json").read_text())["n_volumes"] == 2
