"""`cm2 evaluate`: JSON keys, figures, ground truth as CSV or volume, one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
import typer
from typer.testing import CliRunner

from cm2optics.cli.evaluate import evaluate_command
from cm2optics.formats.emitters import Emitters, write_emitters
from cm2optics.formats.volume import VolumeGrid, write_volume

GRID = VolumeGrid((11, 40, 40), (10.0, 4.15, 4.15))
KEYS = ("recall", "precision", "f1", "jaccard", "rmse_lateral_um", "rmse_axial_um", "n_true", "n_detected")


def _app():
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """test app"""

    app.command("evaluate")(evaluate_command)
    return app


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("evaluate")
    z, y, x = (GRID.axis_um(a) for a in range(3))
    centres = [(3, 10, 12), (7, 25, 30), (5, 33, 8)]
    truth = Emitters(
        [x[c[2]] for c in centres], [y[c[1]] for c in centres], [z[c[0]] for c in centres], [12.0] * 3, [1.0] * 3
    )
    recon = np.zeros(GRID.shape, np.float32)
    gt = np.zeros(GRID.shape, np.float32)
    for iz, iy, ix in centres[:2]:
        recon[iz - 1 : iz + 2, iy - 1 : iy + 2, ix - 1 : ix + 2] = 0.4
        recon[iz, iy, ix] = 1.0
    for iz, iy, ix in centres:
        gt[iz, iy - 1 : iy + 2, ix - 1 : ix + 2] = 1.0
    recon[9, 5, 35] = 0.8  # a false positive
    write_volume(folder / "recon.tif", recon, GRID.voxel_um)
    np.save(folder / "recon.npy", recon)
    write_volume(folder / "gt.tif", gt, GRID.voxel_um)
    write_emitters(folder / "truth.csv", truth)
    return folder


def test_json_has_the_issue_keys_and_known_values(files):
    result = CliRunner().invoke(
        _app(), ["evaluate", str(files / "recon.tif"), str(files / "truth.csv"), "--threshold", "0.5", "--json"]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in KEYS:
        assert key in data, key
    assert (data["n_true"], data["n_detected"], data["n_tp"]) == (3, 3, 2)
    assert data["recall"] == pytest.approx(2 / 3) and data["precision"] == pytest.approx(2 / 3)
    assert data["jaccard"] == pytest.approx(2 / 4)
    assert data["rmse_lateral_um"] == pytest.approx(0.0, abs=1e-6) and data["rmse_axial_um"] == pytest.approx(
        0.0, abs=1e-6
    )
    assert data["threshold"] == 0.5 and data["threshold_source"] == "given"
    assert set(data["breakdowns"]) == {"lateral_mm", "depth_um", "size_um"}
    assert len(data["breakdowns"]["lateral_mm"]) == 7 and len(data["breakdowns"]["depth_um"]) == 9
    assert "recall" in data["maps"] and "NaN" not in result.stdout


def test_f1_optimal_threshold_figures_and_a_volume_as_truth(files, tmp_path):
    result = CliRunner().invoke(
        _app(), ["evaluate", str(files / "recon.tif"), str(files / "gt.tif"), "--json", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["threshold_source"].startswith("F1-optimal") and data["n_true"] == 3
    # above the false positive (0.8) only the two bright centres remain: TP 2, FP 0, FN 1
    assert 0.8 <= data["threshold"] < 1.0 and data["f1"] == pytest.approx(4 / 5)
    for name in ("metrics.json", "breakdowns.png", "maps.png", "overlay.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert json.loads((tmp_path / "metrics.json").read_text())["f1"] == data["f1"]


def test_threshold_from_a_validation_set(files):
    pair = f"{files / 'recon.tif'},{files / 'truth.csv'}"
    result = CliRunner().invoke(
        _app(), ["evaluate", str(files / "recon.tif"), str(files / "truth.csv"), "--validation", pair, "--json"]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["threshold_source"] == "F1-optimal on 1 validation pair(s)"
    line = _one_line_error(
        CliRunner().invoke(
            _app(), ["evaluate", str(files / "recon.tif"), str(files / "truth.csv"), "--validation", "a.tif"]
        )
    )
    assert "RECON,GT" in line


def test_table_output_and_npy_input(files):
    result = CliRunner().invoke(
        _app(),
        ["evaluate", str(files / "recon.npy"), str(files / "truth.csv"), "-t", "0.5", "--voxel-um", "10,4.15,4.15"],
    )
    assert result.exit_code == 0, result.output
    assert "recall" in result.stdout and "0.6667" in result.stdout


def _one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    return lines[0]


def test_errors_are_one_clear_line(files, tmp_path):
    runner = CliRunner()
    assert "no such volume file" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(tmp_path / "none.tif"), str(files / "truth.csv")])
    )
    assert "no such emitter file" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(files / "recon.tif"), str(tmp_path / "none.csv")])
    )
    assert "no voxel spacing" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(files / "recon.npy"), str(files / "truth.csv")])
    )
    assert "--voxel-um" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(files / "recon.tif"), str(files / "truth.csv"), "--voxel-um", "1,2"])
    )
    other = tmp_path / "other.tif"
    write_volume(other, np.zeros((3, 4, 5), np.float32), (10.0, 4.15, 4.15))
    assert "does not match" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(files / "recon.tif"), str(other)])
    )
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y,z\n1,2,3\n")
    assert "columns" in _one_line_error(runner.invoke(_app(), ["evaluate", str(files / "recon.tif"), str(bad)]))
    assert "connectivity" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(files / "recon.tif"), str(files / "truth.csv"), "--connectivity", "5"])
    )
    raw = tmp_path / "measurement.tif"
    tifffile.imwrite(raw, np.ones((40, 40), np.uint16))  # a raw 2-D measurement given as the reconstruction
    assert "not a 3-D volume" in _one_line_error(
        runner.invoke(_app(), ["evaluate", str(raw), str(files / "truth.csv"), "--voxel-um", "10,4.15,4.15"])
    )
    nan = tmp_path / "nan.tif"
    write_volume(nan, np.full((3, 4, 5), np.nan, np.float32), (10.0, 4.15, 4.15))
    assert "NaN" in _one_line_error(runner.invoke(_app(), ["evaluate", str(nan), str(files / "truth.csv")]))
