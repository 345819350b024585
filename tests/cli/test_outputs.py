"""The output policy and the error handler: a user's files are never deleted, bugs are not the user's fault,
interrupted runs resume to the same bytes, and two runs into one folder never mix."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cm2optics.cli import app
from cm2optics.formats.outputs import MARKER, OutputError, check_output
from cm2optics.formats.scan import ScanMeta, read_scan, write_scan

runner = CliRunner()
PACKAGE = Path(__file__).resolve().parents[2] / "cm2optics"
ENV = {**os.environ, "PYTHONPATH": str(PACKAGE.parent)}


def _files(folder: Path, skip: tuple[str, ...] = ("manifest.json", MARKER)) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name not in skip
    }


# ----------------------------------------------------------------------------- the layout


@pytest.mark.parametrize("module", sorted(PACKAGE.rglob("*.py")), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_switches_the_plotting_backend(module: Path):
    """(That no stage imports the command line or the reports is a rule of tests/test_architecture.py.)"""
    assert "matplotlib.use(" not in module.read_text(), f"{module}: switches a notebook user's matplotlib backend"


def test_every_command_that_writes_has_overwrite():
    for args in (
        ["cad", "export"],
        ["spectra", "report"],
        ["illum", "run"],
        ["illum", "optimize"],
        ["psf", "simulate"],
        ["psf", "image"],
        ["lsv", "build"],
        ["simulate"],
        ["synth"],
        ["reconstruct"],
        ["evaluate"],
        ["demo"],
        ["compare-baselines"],
    ):
        result = runner.invoke(app, [*args, "--help"])
        assert result.exit_code == 0 and "--overwrite" in result.output, args


# ----------------------------------------------------------------------------- the policy


def _scan(folder: Path, value: int) -> Path:
    images = np.full((2, 8, 8), value, np.uint16)
    positions = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.1]])
    return write_scan(folder, images, positions, 1.0, ScanMeta(pixel_um=2.0, binning=1, bit_depth=12, dark_level=0))


def test_write_scan_never_removes_a_users_files(tmp_path):
    folder = tmp_path / "scan"
    folder.mkdir()
    (folder / "notes.md").write_text("mine")
    _scan(folder, 5)
    assert (folder / "notes.md").read_text() == "mine"
    assert read_scan(folder).images.max() == 5
    _scan(folder, 7)  # its own earlier output: replaced, the user's file still there
    assert (folder / "notes.md").read_text() == "mine" and read_scan(folder).images.max() == 7


def test_write_scan_into_the_working_folder_keeps_everything(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "thesis.tex").write_text("years of work")
    _scan(Path("."), 3)
    assert (tmp_path / "thesis.tex").read_text() == "years of work"
    assert read_scan(tmp_path).images.max() == 3


def test_a_rerun_replaces_its_own_folder_whole(tmp_path):
    folder = _scan(tmp_path / "s", 1)
    (folder / "psf_00099.tif").unlink(missing_ok=True)
    _scan(folder, 2)
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        [MARKER, "positions.csv", "psf_00000.tif", "psf_00001.tif", "scan.yaml"]
    )


def test_check_output_rules(tmp_path):
    (tmp_path / "in.tif").write_text("x")
    (tmp_path / "own").mkdir()
    (tmp_path / "own" / MARKER).write_text('{"command": "synth"}')
    (tmp_path / "own" / "a").write_text("x")
    check_output(tmp_path / "own", command="synth", kind="folder")  # its own folder: fine
    with pytest.raises(OutputError, match="not empty"):
        check_output(tmp_path / "own", command="demo", kind="folder")
    check_output(tmp_path / "own", command="demo", kind="folder", overwrite=True)
    with pytest.raises(OutputError, match="input"):
        check_output(tmp_path / "in.tif", command="x", inputs=[tmp_path / "in.tif"], overwrite=True)
    with pytest.raises(OutputError, match="in.tif is a file"):
        check_output(tmp_path / "in.tif" / "x" / "y.tif", command="x")


def test_overwrite_replaces_an_earlier_file(tmp_path):
    from cm2optics.design import load_preset
    from cm2optics.lsv.toy import analytic_lsv_model_file as analytic_model

    model = analytic_model(
        tmp_path / "m.lsv.h5", load_preset("cm2-v2"), binning=8, rank=4, lateral_nodes=7, depth_nodes=3
    )
    emitters = tmp_path / "e.csv"
    emitters.write_text("x_um,y_um,z_um,diameter_um,intensity\n0,0,0,10,1\n")
    out = tmp_path / "meas.tif"
    out.write_text("an earlier file")
    args = ["simulate", "--model", str(model), "--emitters", str(emitters), "--out", str(out)]
    refused = runner.invoke(app, args)
    assert refused.exit_code == 2 and "--overwrite" in refused.stderr and out.read_text() == "an earlier file"
    done = runner.invoke(app, [*args, "--overwrite"])
    assert done.exit_code == 0, done.output
    assert out.read_bytes()[:2] == b"II"


# ----------------------------------------------------------------------------- errors


def _broken(*args, **kwargs):
    np.zeros(3) + np.zeros(4)  # a bug: numpy raises ValueError


def test_a_library_bug_is_an_internal_error_not_the_users_fault(monkeypatch):
    monkeypatch.setattr("cm2optics.reports.design.design_summary", _broken)
    monkeypatch.delenv("CM2_DEBUG", raising=False)
    result = runner.invoke(app, ["design", "show"])
    assert result.exit_code == 3
    assert "internal error" in result.stderr and "bug" in result.stderr and "Traceback" not in result.stderr
    written = result.stderr.split("traceback written to ")[1].split(";")[0].strip()
    assert "Traceback" in Path(written).read_text()
    Path(written).unlink()


@pytest.mark.parametrize("how", ["--debug", "CM2_DEBUG"])
def test_debug_shows_tracebacks(monkeypatch, how):
    monkeypatch.setattr("cm2optics.reports.design.design_summary", _broken)
    if how == "CM2_DEBUG":
        monkeypatch.setenv("CM2_DEBUG", "1")
        result = runner.invoke(app, ["design", "show"])
    else:
        monkeypatch.delenv("CM2_DEBUG", raising=False)
        result = runner.invoke(app, ["--debug", "design", "show"])
    assert result.exit_code == 3 and "Traceback" in result.stderr
    user = runner.invoke(app, ["--debug", "design", "validate", "/no/such/design.yaml"])
    assert user.exit_code == 2 and "Traceback" in user.stderr  # user errors too, under --debug
    runner.invoke(app, ["design", "presets"])


# ----------------------------------------------------------------------------- interrupts and races


def _default_interrupts() -> None:
    """In the child before exec: Ctrl-C and SIGTERM as a terminal delivers them. A disposition
    set to 'ignore' is inherited across exec (and Python then installs no KeyboardInterrupt), and
    a library used by an earlier test in this pytest process may have left SIGINT ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _cm2(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "cm2optics.cli", *args],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_default_interrupts,
    )


# five positions: room to interrupt after the first, even on a loaded machine
PSF = ["psf", "simulate", "--grid", "1x1x5", "--binning", "8", "--workers", "1", "--json"]


@pytest.fixture(scope="module")
def psf_reference(tmp_path_factory) -> dict[str, str]:
    """Two runs at once into one folder: one refuses (or both finish); the folder is one whole scan."""
    out = tmp_path_factory.mktemp("race") / "scan"
    first, second = _cm2(*PSF, "--out", str(out)), _cm2(*PSF, "--out", str(out))
    results = [(p.wait(timeout=300), p.stderr.read()) for p in (first, second)]
    codes = sorted(code for code, _ in results)
    assert codes in ([0, 0], [0, 2]), results
    if codes == [0, 2]:
        assert "another `cm2 psf simulate` is writing there" in [e for c, e in results if c == 2][0]
    assert read_scan(out).images.shape[0] == 5
    assert not list(out.parent.glob(".scan*")), "work, staging or lock folders left behind"
    return _files(out)


def _interrupt_when(process: subprocess.Popen, ready, sig: int, timeout_s: float = 240) -> int:
    start = time.monotonic()
    while not ready():
        assert process.poll() is None, process.stderr.read()
        assert time.monotonic() - start < timeout_s
        time.sleep(0.05)
    process.send_signal(sig)
    return process.wait(timeout=120)


@pytest.mark.parametrize(
    "sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)], ids=["SIGINT", "SIGTERM"]
)
def test_psf_simulate_resumes_to_identical_bytes(tmp_path, psf_reference, sig):
    out = tmp_path / "scan"
    work = tmp_path / ".scan.psf-work"
    code = _interrupt_when(_cm2(*PSF, "--out", str(out)), lambda: len(list(work.glob("pos_*.npz"))) >= 1, sig)
    assert code == 130
    assert not out.exists(), "an interrupted scan left a half-written folder"
    resumed = _cm2(*PSF, "--out", str(out))
    assert resumed.wait(timeout=300) == 0, resumed.stderr.read()
    assert _files(out) == psf_reference
    assert not work.exists()


SYNTH = ["synth", "-n", "4", "--workers", "0", "--size", "scaled", "--seed", "3", "--export", "4", "--json"]


@pytest.fixture(scope="module")
def synth_model(tmp_path_factory) -> Path:
    from cm2optics.design import load_preset
    from cm2optics.lsv.toy import analytic_lsv_model_file as analytic_model

    root = tmp_path_factory.mktemp("synth-model")
    model = analytic_model(root / "m.lsv.h5", load_preset("cm2-v2"), binning=8, rank=4, lateral_nodes=7, depth_nodes=3)
    done = _cm2(*SYNTH, "--model", str(model), "--out", str(root / "reference"))
    assert done.wait(timeout=300) == 0, done.stderr.read()
    return model


@pytest.mark.parametrize(
    "sig", [pytest.param(signal.SIGINT, marks=pytest.mark.slow), signal.SIGTERM], ids=["SIGINT", "SIGTERM"]
)
def test_synth_resumes_to_identical_bytes(tmp_path, synth_model, sig):
    reference = synth_model.parent / "reference"
    out = tmp_path / "set"
    process = _cm2(*SYNTH, "--model", str(synth_model), "--out", str(out))
    code = _interrupt_when(process, lambda: len(list((out / "samples").glob("sample_*.h5"))) >= 1, sig)
    if code == 0:
        pytest.skip("the run finished before the signal arrived")
    assert code == 130, process.stderr.read()
    resumed = _cm2(*SYNTH, "--model", str(synth_model), "--out", str(out))
    assert resumed.wait(timeout=300) == 0, resumed.stderr.read()
    assert _files(out / "export") == _files(reference / "export")


def test_clamped_options_are_said_aloud(tmp_path):
    from cm2optics.design import load_preset
    from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan

    xs = np.linspace(-1.2, 1.2, 3)
    scan = write_analytic_scan(
        tmp_path / "scan", AnalyticCM2.from_design(load_preset("cm2-v2"), binning=8), xs, xs, [-0.1, 0.1], binning=8
    )
    result = runner.invoke(app, ["lsv", "build", str(scan), "--rank", "500", "--no-report", "--json"])
    assert result.exit_code == 0, result.output
    assert "warning: --rank 500: the scan's 18 positions allow only 18 basis PSFs" in result.stderr
    assert json.loads(result.stdout)["rank"] < 500  # stdout stays JSON
