"""`cm2 illum`: JSON keys, one clear error for bad STLs and options, the scalar fallback."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from cm2optics.cli.illum import illum_app

runner = CliRunner()
KEYS = (
    "throughput",
    "throughput_stderr",
    "delivered_fraction",
    "delivered_fraction_stderr",
    "uniformity_cv",
    "power_mw",
    "rays",
)


def _one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    return lines[0]


def test_help_defines_every_figure():
    result = runner.invoke(illum_app, ["--help"])
    assert result.exit_code == 0
    for name in ("throughput", "delivered_fraction", "power_mw", "uniformity_cv", "ledger"):
        assert name in result.output
    result = runner.invoke(illum_app, ["run", "--help"])
    for option in ("--collimator", "--led-position", "--led-axis", "--rays", "--json"):
        assert option in result.output


def test_run_json_compares_v1_and_the_design(tmp_path):
    result = runner.invoke(
        illum_app, ["run", "--preset", "cm2-v2", "--rays", "40000", "--json", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in KEYS:
        assert key in data, key
    assert data["rays"] == 40000
    assert len(data["per_led"]) == 4
    assert set(data["designs"]) == {"V1: bare LED + filter", "cm2-v2 (CAD)"}
    v1, v2 = data["designs"]["V1: bare LED + filter"], data["designs"]["cm2-v2 (CAD)"]
    assert v2["delivered_fraction"] > 2 * v1["delivered_fraction"]
    assert 0 < data["delivered_fraction"] < data["throughput"] < 1
    assert data["power_mw"] == pytest.approx(4 * 640.0 * data["delivered_fraction"], rel=1e-3)
    assert abs(sum(data["ledger"][k] for k in ("delivered", "absorbed", "escaped")) - 1) < 1e-9
    assert (tmp_path / "illumination.json").is_file()
    assert len(list(tmp_path.glob("irradiance_*.png"))) == 2


def _write_stl(mesh: trimesh.Trimesh, path) -> str:
    mesh.export(path)
    return str(path)


def test_stl_that_is_not_watertight_is_one_clear_error(tmp_path):
    box = trimesh.creation.box(extents=[3, 3, 1.5])
    box.apply_translation([0, 0, 1.0])
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    path = _write_stl(open_box, tmp_path / "open.stl")
    line = _one_line_error(
        runner.invoke(illum_app, ["run", "--collimator", path, "--rays", "4000", "--out", str(tmp_path / "o")])
    )
    assert "not watertight" in line
    assert not (tmp_path / "o").exists()


def test_empty_stl_is_one_clear_error(tmp_path):
    path = tmp_path / "empty.stl"
    path.write_bytes(b"\0" * 80 + (0).to_bytes(4, "little"))
    line = _one_line_error(runner.invoke(illum_app, ["run", "--collimator", str(path), "--rays", "4000"]))
    assert "empty" in line


def test_led_inside_the_solid_is_one_clear_error(tmp_path):
    box = trimesh.creation.box(extents=[3, 3, 1.5])  # centred on the LED
    path = _write_stl(box, tmp_path / "solid.stl")
    line = _one_line_error(
        runner.invoke(illum_app, ["run", "--collimator", path, "--led-position", "0,0,-0.7", "--rays", "4000"])
    )
    assert "LED sits inside" in line


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--led-position", "0,0,1"], "give the STL with --collimator"),
        (["--rays", "10"], "--rays"),
        (["--bin-mm", "0"], "--bin-mm"),
    ],
)
def test_bad_options_are_one_clear_error(args, message):
    line = _one_line_error(runner.invoke(illum_app, ["run", *args]))
    assert message in line


def test_scalar_fallback_runs_and_says_so_once(tmp_path):
    """Without the LLVM library the tracer falls back to Mitsuba's scalar variant, warns
    once, and traces the same rays to the same fates."""
    script = textwrap.dedent(
        """
        import json, warnings
        warnings.simplefilter("always")
        import numpy as np
        from cm2optics.design import load_preset
        from cm2optics.optics.backend import variant
        from cm2optics.illumination.geometry import build_scene
        from cm2optics.illumination.source import led_source
        from cm2optics.illumination.excitation import design_filter_transmission
        from cm2optics.illumination.tracer import trace
        design = load_preset("cm2-v2")
        scene = build_scene(design, None)
        source = led_source(design)
        T = design_filter_transmission(design)
        a = trace(scene, source, 200, transmission=T, seed=4)
        b = trace(scene, source, 200, transmission=T, seed=4)
        print(json.dumps({"variant": variant().variant, "status": a.status.tolist(), "same": bool((a.status == b.status).all())}))
        """
    )
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": str(tmp_path / "missing" / "libLLVM.so.19")}
    env.pop("CM2_ILLUM_VARIANT", None)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout.strip().splitlines()[-1])
    assert data["variant"] == "scalar_rgb" and data["same"]
    warnings = [line for line in result.stderr.splitlines() if "scalar variant" in line]
    assert len(warnings) == 1, result.stderr
    # The vectorised tracer gives the same fates to the same rays (float rounding aside).
    from cm2optics.design import load_preset
    from cm2optics.illumination.excitation import design_filter_transmission
    from cm2optics.illumination.geometry import build_scene
    from cm2optics.illumination.source import led_source
    from cm2optics.illumination.tracer import trace

    design = load_preset("cm2-v2")
    ours = trace(
        build_scene(design, None), led_source(design), 200, transmission=design_filter_transmission(design), seed=4
    )
    assert np.mean(ours.status == np.array(data["status"])) > 0.95


def test_run_reports_the_spectral_ceiling_of_its_own_inputs(tmp_path, reference_dir):
    """`cm2 illum run` with the authors' coating table and LED spectrum: its spectral ceiling is
    theirs (≈ 86 %), not the model filter's (≈ 79 %)."""
    args = ["run", "--preset", "cm2-v2", "--rays", "4000", "--out", str(tmp_path)]
    inputs = ["--filter-table", str(reference_dir / "coating_real_ex.csv")]
    inputs += ["--led-spectrum", str(reference_dir / "led_spectrum.csv")]
    result = runner.invoke(illum_app, [*args, *inputs])
    assert result.exit_code == 0, result.output
    printed = re.search(r"passes at most\s+(\d+\.\d)%", result.stdout)
    assert printed is not None, result.stdout
    data = json.loads((tmp_path / "illumination.json").read_text())
    assert data["spectral_ceiling"] == pytest.approx(0.86, abs=0.015)
    assert float(printed.group(1)) == pytest.approx(100 * data["spectral_ceiling"], abs=0.05)
