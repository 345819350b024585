"""``cm2 calibrate scan``: bad data get one clear error before any tracing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from cm2optics.cli import app
from cm2optics.formats.scan import ScanMeta, write_scan

runner = CliRunner()


def _scan(folder: Path, shape: tuple[int, int], pixel_um: float = 19.2, binning: int = 8) -> Path:
    positions = np.array([[x, 0.0, z] for z in (-0.1, 0.1) for x in (-0.5, 0.5)])
    images = np.full((len(positions),) + shape, 100, np.uint16)
    meta = ScanMeta(pixel_um=pixel_um, binning=binning, bit_depth=12, dark_level=100.0, extra={"lenslets": [3, 3]})
    return write_scan(folder, images, positions, 1.0, meta)


def test_a_scan_of_the_wrong_sensor_size_is_refused(tmp_path: Path):
    scan = _scan(tmp_path / "scan", (100, 120))
    result = runner.invoke(app, ["calibrate", "scan", str(scan), "--out", str(tmp_path / "report")])
    assert result.exit_code == 2, result.output
    assert "wrong sensor size" in result.output and "259 × 386" in result.output
    assert not (tmp_path / "report").exists()


def test_a_pixel_pitch_that_contradicts_the_binning_is_refused(tmp_path: Path):
    scan = _scan(tmp_path / "scan", (259, 386), pixel_um=9.6)
    result = runner.invoke(app, ["calibrate", "scan", str(scan), "--out", str(tmp_path / "report")])
    assert result.exit_code == 2 and "pixel_um" in result.output


def test_the_report_may_not_overwrite_the_scan(tmp_path: Path):
    scan = _scan(tmp_path / "scan", (259, 386))
    result = runner.invoke(app, ["calibrate", "scan", str(scan), "--out", str(scan / "report")])
    assert result.exit_code == 2 and "inside the input folder" in result.output


def test_a_source_profile_that_cannot_be_read_is_refused(tmp_path: Path):
    scan = _scan(tmp_path / "scan", (259, 386))
    out = tmp_path / "report"
    result = runner.invoke(app, ["calibrate", "scan", str(scan), "--out", str(out), "--source-profile", "conical"])
    assert result.exit_code == 2, result.output
    assert "calibration source" in result.output and "'conical'" in result.output
    assert "Traceback" not in result.output and not out.exists()
