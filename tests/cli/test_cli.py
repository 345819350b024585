"""The `cm2` command: help that teaches, JSON output, one clear error and exit 2 on bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from cm2optics.cli import app
from cm2optics.optics import first_order

runner = CliRunner()


def test_help_lists_the_stages():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("design", "cad", "demo"):
        assert command in result.output


def test_cad_export_help_documents_units_and_manifest():
    result = runner.invoke(app, ["cad", "export", "--help"])
    assert result.exit_code == 0
    for text in ("--tolerance-um", "--format", "interferences", "device", "µm"):
        assert text in result.output


def test_design_show_json(v2):
    result = runner.invoke(app, ["design", "show", "--preset", "cm2-v2", "--json"])
    assert result.exit_code == 0
    data = json.loads(result.stdout)
    assert data["magnification"] == pytest.approx(first_order.magnification(v2), abs=1e-4)
    assert data["object_pixel_um"] == pytest.approx(4.15, rel=0.02)


def test_design_yaml_round_trips_through_validate(tmp_path):
    result = runner.invoke(app, ["design", "show", "--yaml"])
    path = tmp_path / "mine.yaml"
    path.write_text(result.stdout)
    assert runner.invoke(app, ["design", "validate", str(path)]).exit_code == 0


def _one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    assert "Traceback" not in result.output
    return lines[0]


def test_bad_preset_is_one_clear_error():
    line = _one_line_error(runner.invoke(app, ["design", "show", "--preset", "cm9"]))
    assert "unknown preset" in line and "cm2-v2" in line


def test_bad_design_file_names_the_field(tmp_path, v2):
    path = tmp_path / "bad.yaml"
    path.write_text(v2.to_yaml().replace("radius_mm: 1.65", "radius_mm: -1.65"))
    line = _one_line_error(runner.invoke(app, ["design", "validate", str(path)]))
    assert "mla.radius_mm" in line and "-1.65" in line


@pytest.mark.parametrize(
    ("option", "value", "message"), [("--format", "obj", "allowed formats"), ("--tolerance-um", "0", "0.1–100")]
)
def test_bad_export_options_leave_nothing_behind(tmp_path, option, value, message):
    out = tmp_path / "cad"
    line = _one_line_error(runner.invoke(app, ["cad", "export", "--out", str(out), option, value]))
    assert message in line
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_console_script_entry_point():
    result = subprocess.run(
        [sys.executable, "-m", "cm2optics.cli", "--version"], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0 and "cm2optics" in result.stdout
