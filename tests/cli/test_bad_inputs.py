"""The bad-input catalogue: every `cm2` command against every kind of mistake a user can make.

Each case runs the command in-process and asserts: exit status 2 (or the status the case names),
one line on stderr naming the file or the option, no traceback, and that no file in the inputs
folder or the case's folder changed, disappeared or appeared (checksums before and after).
Cases fail before any heavy work, so the whole catalogue runs in seconds.

Classes: output-is-input, output-under-file, output-kind (a folder where a file goes or the
reverse), existing-output (an earlier file or a foreign non-empty folder without --overwrite),
input-file (missing, a folder, garbage), option (bad values and lists), size-guard (before
allocation), dask (an unreachable scheduler).
"""

from __future__ import annotations

import collections
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import tifffile
from typer.testing import CliRunner

from cm2optics.cli import app

runner = CliRunner()
SHIPPED_WEIGHTS = Path(__file__).resolve().parents[2] / "reconstruction" / "cm2net-cpu"


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Inputs shared by every case (read-only by contract: their checksums are checked)."""
    from cm2optics.design import load_preset
    from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan
    from cm2optics.lsv.toy import analytic_lsv_model_file as analytic_model

    root = tmp_path_factory.mktemp("inputs")
    design = load_preset("cm2-v2")
    xs = np.linspace(-1.2, 1.2, 3)
    scan = write_analytic_scan(
        root / "scan", AnalyticCM2.from_design(design, binning=8), xs, xs, np.linspace(-0.2, 0.2, 3), binning=8
    )
    model = analytic_model(root / "model.lsv.h5", design, binning=8, rank=4, lateral_nodes=7, depth_nodes=3)
    (root / "emitters.csv").write_text("x_um,y_um,z_um,diameter_um,intensity\n0,0,0,10,1\n")
    (root / "positions.csv").write_text("x_mm,y_mm,z_mm\n0,0,0\n")
    (root / "meas.tif").write_bytes(b"II*\x00" + bytes(range(256)) * 4)  # any existing file: refused before reading
    (root / "garbage.tif").write_bytes(os.urandom(2048))
    tifffile.imwrite(root / "map.tif", np.full((64, 64), 100.0, np.float32))  # a valid 64 × 64 map
    (root / "garbage.h5").write_bytes(os.urandom(2048))
    (root / "garbage.csv").write_bytes(b"\x00\xff\xfe not,a,csv\n\x01\x02")
    (root / "garbage.yaml").write_text("mla: [unclosed\n  : :\n")
    (root / "garbage.stl").write_bytes(os.urandom(300))
    (root / "curves.csv").write_text("wavelength_nm,aoi_deg,T\n500,0,0.5\n")
    (root / "adir.tif").mkdir()
    np.save(root / "beads.npy", np.full((design.sensor.height_px // 16, design.sensor.width_px // 16), 100.0))
    np.save(root / "small.npy", np.full((100, 120), 100.0))
    np.save(root / "nan.npy", np.full((design.sensor.height_px // 16, design.sensor.width_px // 16), np.nan))
    (root / "regular").write_text("a user's file\n")
    return {
        "root": root,
        "scan": scan,
        "model": model,
        "emitters": root / "emitters.csv",
        "positions": root / "positions.csv",
        "meas": root / "meas.tif",
        "map": root / "map.tif",
        "garbage_tif": root / "garbage.tif",
        "garbage_h5": root / "garbage.h5",
        "garbage_csv": root / "garbage.csv",
        "garbage_yaml": root / "garbage.yaml",
        "garbage_stl": root / "garbage.stl",
        "curves": root / "curves.csv",
        "adir": root / "adir.tif",
        "beads": root / "beads.npy",
        "nan_frame": root / "nan.npy",
        "small_frame": root / "small.npy",
        "regular": root / "regular",
        "missing": root / "missing.tif",
    }


def _tree(*folders: Path) -> dict[str, str]:
    """Checksums of every file (and the names of every folder) under ``folders``."""
    sums = {}
    for folder in folders:
        for path in sorted(folder.rglob("*")):
            sums[str(path)] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "dir"
    return sums


# ----------------------------------------------------------------------------- cases


@dataclass
class Case:
    command: str  # the `cm2` command, for the count
    kind: str  # the class of mistake, for the count
    args: list[str]  # with {placeholders} of inputs and {case} (the case's own folder)
    expect: tuple[str, ...]  # text the one-line message must hold (the file or the option)
    setup: dict[str, str] = field(default_factory=dict)  # files to create in {case}: name → text ("/": folder)
    code: int = 2
    cwd: bool = False  # run inside {case} (``--out .``)


# What each writing command needs besides its output (valid, so that the output is what is wrong).
FOLDER_WRITERS = {
    "cad export": ["cad", "export", "--no-pictures", "--format", "stl", "--out"],
    "spectra report": ["spectra", "report", "--out"],
    "illum run": ["illum", "run", "--rays", "1000", "--out"],
    "illum optimize": ["illum", "optimize", "--rays", "1000", "--out"],
    "illum robustness": ["illum", "robustness", "--samples", "2", "--rays", "1000", "--out"],
    "psf simulate": ["psf", "simulate", "--grid", "1x1x1", "--binning", "8", "--out"],
    "synth": ["synth", "--model", "{model}", "-n", "1", "--workers", "0", "--size", "scaled", "--out"],
    "evaluate": ["evaluate", "{meas}", "{emitters}", "--out"],
    "demo": ["demo", "--out"],
    "lsv build --report": ["lsv", "build", "{scan}", "--out", "{case}/m.lsv.h5", "--report"],
}
FILE_WRITERS = {
    "psf image": ["psf", "image", "--emitters", "{emitters}", "--binning", "8", "--out"],
    "lsv build": ["lsv", "build", "{scan}", "--no-report", "--out"],
    "simulate": ["simulate", "--model", "{model}", "--emitters", "{emitters}", "--out"],
    "reconstruct": ["reconstruct", "{meas}", "--model", "{model}", "--out"],
}


def _command(name: str) -> str:
    return name.split(" --")[0]


def _output_cases() -> list[Case]:
    cases = []
    for name, args in FOLDER_WRITERS.items():
        cmd = _command(name)
        cases += [
            Case(cmd, "output-under-file", [*args, "{regular}/out"], ("regular", "is a file")),
            Case(cmd, "output-kind", [*args, "{case}/f"], ("f", "is a file"), {"f": "mine\n"}),
            Case(cmd, "existing-output", [*args, "{case}"], ("--out", "not empty", "--overwrite"), {"keep.txt": "x\n"}),
            Case(
                cmd,
                "existing-output",
                [*args, "{case}/d"],
                ("not empty", "--overwrite"),
                {"d/": "", "d/notes.md": "x\n", "d/sub/": ""},
            ),
            Case(cmd, "existing-output", [*args, "."], ("not empty",), {"keep.txt": "x\n"}, cwd=True),
        ]
    for name, args in FILE_WRITERS.items():
        cmd = _command(name)
        suffix = ".h5" if cmd == "lsv build" else ".tif"
        cases += [
            Case(cmd, "output-under-file", [*args, f"{{regular}}/out{suffix}"], ("regular", "is a file")),
            Case(cmd, "output-kind", [*args, "{adir}"], ("adir.tif", "is a folder")),
            Case(
                cmd, "existing-output", [*args, f"{{case}}/old{suffix}"], ("old", "--overwrite"), {f"old{suffix}": "1"}
            ),
            Case(cmd, "output-under-file", [*args, f"{{case}}/a/b/c{suffix}"], ("a", "is a file"), {"a": "file"}),
        ]
    cases += [
        Case("psf image", "output-is-input", FILE_WRITERS["psf image"] + ["{emitters}"], ("emitters.csv", "input")),
        Case("lsv build", "output-is-input", ["lsv", "build", "{scan}", "--out", "{scan}/psf_00000.tif"], ("scan",)),
        Case("lsv build", "output-is-input", ["lsv", "build", "{scan}", "--out", "{scan}/positions.csv"], ("scan",)),
        Case("lsv build", "output-kind", ["lsv", "build", "{scan}", "--out", "{root}"], ("is a folder",)),
        Case(
            "simulate",
            "output-is-input",
            ["simulate", "--model", "{model}", "--volume", "{meas}", "--out", "{meas}"],
            ("meas.tif", "input"),
        ),
        Case(
            "simulate",
            "output-is-input",
            ["simulate", "--model", "{model}", "--emitters", "{emitters}", "--out", "{model}"],
            ("model.lsv.h5",),
        ),
        Case("reconstruct", "output-is-input", FILE_WRITERS["reconstruct"] + ["{meas}"], ("meas.tif", "input")),
        Case("reconstruct", "output-is-input", FILE_WRITERS["reconstruct"] + ["{model}"], ("model.lsv.h5", "input")),
        Case(
            "psf simulate",
            "output-is-input",
            ["psf", "simulate", "--positions", "{case}/p/pos.csv", "--out", "{case}/p"],
            ("pos.csv", "input"),
            {"p/": "", "p/pos.csv": "x_mm,y_mm,z_mm\n0,0,0\n"},
        ),
        Case(
            "evaluate",
            "output-is-input",
            ["evaluate", "{case}/e/r.tif", "{emitters}", "--out", "{case}/e"],
            ("r.tif", "input"),
            {"e/": "", "e/r.tif": "x"},
        ),
        Case("synth", "output-is-input", ["synth", "--model", "{model}", "--out", "{root}"], ("model.lsv.h5", "input")),
        Case("synth", "existing-output", ["synth", "--model", "{model}", "--out", "{scan}"], ("not empty",)),
        Case("compare-baselines", "output-is-input", ["compare-baselines", "{model}", "{root}"], ("input",)),
        Case(
            "compare-baselines",
            "existing-output",
            ["compare-baselines", "{model}", "{case}"],
            ("not empty",),
            {"k": "x"},
        ),
        Case("compare-baselines", "output-under-file", ["compare-baselines", "{model}", "{regular}/o"], ("regular",)),
        Case(
            "illum run",
            "output-is-input",
            ["illum", "run", "--collimator", "{case}/o/c.stl", "--out", "{case}/o"],
            ("c.stl", "input"),
            {"o/": "", "o/c.stl": "solid"},
        ),
    ]
    return cases


def _input_cases() -> list[Case]:
    return [
        # missing files, folders given as files, garbage
        Case("design validate", "input-file", ["design", "validate", "{missing}"], ("missing.tif",)),
        Case("design validate", "input-file", ["design", "validate", "{adir}"], ("adir.tif", "folder")),
        Case("design validate", "input-file", ["design", "validate", "{garbage_yaml}"], ("garbage.yaml",)),
        Case("design show", "input-file", ["design", "show", "--preset", "{garbage_yaml}"], ("garbage.yaml",)),
        Case("cad export", "input-file", ["cad", "export", "--preset", "{missing}", "--out", "{case}/o"], ("missing",)),
        Case("spectra fit-filter", "input-file", ["spectra", "fit-filter", "{missing}"], ("missing.tif",)),
        Case("spectra fit-filter", "input-file", ["spectra", "fit-filter", "{adir}"], ("adir.tif", "folder")),
        Case("spectra fit-filter", "input-file", ["spectra", "fit-filter", "{garbage_csv}"], ("garbage.csv",)),
        Case("spectra fit-filter", "input-file", ["spectra", "fit-filter", "{curves}"], ("curves.csv",)),
        Case(
            "illum run",
            "input-file",
            ["illum", "run", "--rays", "1000", "--collimator", "{missing}", "--out", "{case}/o"],
            ("missing.tif",),
        ),
        Case(
            "illum run",
            "input-file",
            ["illum", "run", "--rays", "1000", "--collimator", "{garbage_stl}", "--out", "{case}/o"],
            ("garbage.stl",),
        ),
        Case(
            "illum run",
            "input-file",
            ["illum", "run", "--rays", "1000", "--led-profile", "{garbage_csv}", "--out", "{case}/o"],
            ("garbage.csv",),
        ),
        Case(
            "illum run",
            "input-file",
            ["illum", "run", "--rays", "1000", "--led-spectrum", "{adir}", "--out", "{case}/o"],
            ("adir.tif", "folder"),
        ),
        Case(
            "psf simulate",
            "input-file",
            ["psf", "simulate", "--positions", "{missing}", "--out", "{case}/o"],
            ("missing.tif",),
        ),
        Case(
            "psf simulate",
            "input-file",
            ["psf", "simulate", "--positions", "{garbage_csv}", "--out", "{case}/o"],
            ("garbage.csv",),
        ),
        Case(
            "psf image",
            "input-file",
            ["psf", "image", "--emitters", "{missing}", "--out", "{case}/m.tif"],
            ("missing.tif",),
        ),
        Case(
            "psf image",
            "input-file",
            ["psf", "image", "--emitters", "{garbage_csv}", "--out", "{case}/m.tif"],
            ("garbage.csv",),
        ),
        Case("lsv build", "input-file", ["lsv", "build", "{missing}", "--out", "{case}/m.h5"], ("missing.tif",)),
        Case("lsv build", "input-file", ["lsv", "build", "{regular}", "--out", "{case}/m.h5"], ("regular",)),
        Case(
            "lsv build",
            "input-file",
            ["lsv", "build", "{case}/empty", "--out", "{case}/m.h5"],
            ("empty",),
            {"empty/": ""},
        ),
        Case("lsv validate", "input-file", ["lsv", "validate", "{garbage_h5}", "{scan}"], ("garbage.h5",)),
        Case("lsv validate", "input-file", ["lsv", "validate", "{missing}", "{scan}"], ("missing.tif",)),
        Case("lsv validate", "input-file", ["lsv", "validate", "{model}", "{missing}"], ("missing.tif",)),
        Case(
            "simulate",
            "input-file",
            ["simulate", "--model", "{garbage_h5}", "--emitters", "{emitters}", "--out", "{case}/m.tif"],
            ("garbage.h5",),
        ),
        Case(
            "simulate",
            "input-file",
            ["simulate", "--model", "{model}", "--emitters", "{garbage_csv}", "--out", "{case}/m.tif"],
            ("garbage.csv",),
        ),
        Case(
            "simulate",
            "input-file",
            ["simulate", "--model", "{model}", "--volume", "{garbage_tif}", "--out", "{case}/m.tif"],
            ("garbage.tif",),
        ),
        Case(
            "simulate",
            "input-file",
            ["simulate", "--model", "{model}", "--volume", "{adir}", "--out", "{case}/m.tif"],
            ("adir.tif", "folder"),
        ),
        Case("synth", "input-file", ["synth", "--model", "{garbage_h5}", "--out", "{case}/s"], ("garbage.h5",)),
        Case("synth", "input-file", ["synth", "--model", "{missing}", "--out", "{case}/s"], ("missing.tif",)),
        Case(
            "synth",
            "input-file",
            ["synth", "--model", "{model}", "--config", "{garbage_yaml}", "--out", "{case}/s"],
            ("garbage.yaml",),
        ),
        Case(
            "reconstruct",
            "input-file",
            ["reconstruct", "{garbage_tif}", "--model", "{model}", "--out", "{case}/v.tif"],
            ("garbage.tif",),
        ),
        Case(
            "reconstruct",
            "input-file",
            ["reconstruct", "{adir}", "--model", "{model}", "--out", "{case}/v.tif"],
            ("adir.tif", "folder"),
        ),
        Case(
            "reconstruct",
            "input-file",
            ["reconstruct", "{missing}", "--model", "{model}", "--out", "{case}/v.tif"],
            ("missing.tif",),
        ),
        Case(
            "reconstruct",
            "input-file",
            ["reconstruct", "{meas}", "--model", "{garbage_h5}", "--out", "{case}/v.tif"],
            ("garbage.h5",),
        ),
        Case("evaluate", "input-file", ["evaluate", "{garbage_tif}", "{emitters}"], ("garbage.tif",)),
        Case("evaluate", "input-file", ["evaluate", "{missing}", "{emitters}"], ("missing.tif",)),
        Case("evaluate", "input-file", ["evaluate", "{adir}", "{emitters}"], ("adir.tif",)),
        Case("demo", "input-file", ["demo", "--preset", "{garbage_yaml}", "--out", "{case}/d"], ("garbage.yaml",)),
        # option values and lists
        Case("psf simulate", "option", ["psf", "simulate", "--grid", "9x9", "--out", "{case}/o"], ("--grid",)),
        Case("psf simulate", "option", ["psf", "simulate", "--grid", "0x1x1", "--out", "{case}/o"], ("--grid",)),
        Case("psf simulate", "option", ["psf", "simulate", "--grid", "axbxc", "--out", "{case}/o"], ("--grid",)),
        Case(
            "psf simulate",
            "option",
            ["psf", "simulate", "--grid", "1x1x1", "--positions", "{positions}", "--out", "{case}/o"],
            ("--grid", "--positions"),
        ),
        Case(
            "psf simulate",
            "option",
            ["psf", "simulate", "--grid", "1x1x1", "--binning", "0", "--out", "{case}/o"],
            ("binning",),
        ),
        Case(
            "psf image",
            "option",
            ["psf", "image", "--emitters", "{emitters}", "--binning", "99", "--out", "{case}/m.tif"],
            ("binning",),
        ),
        Case("lsv build", "option", ["lsv", "build", "{scan}", "--rank", "0", "--out", "{case}/m.h5"], ("--rank",)),
        Case("lsv build", "option", ["lsv", "build", "{scan}", "--trim", "1", "--out", "{case}/m.h5"], ("--trim",)),
        Case(
            "lsv build",
            "option",
            ["lsv", "build", "{scan}", "--axial-um", "-1", "--out", "{case}/m.h5"],
            ("--axial-um",),
        ),
        Case("lsv validate", "option", ["lsv", "validate", "{model}", "{scan}", "--ranks", "0,4"], ("--ranks",)),
        Case("lsv validate", "option", ["lsv", "validate", "{model}", "{scan}", "--ranks", "a,b"], ("--ranks",)),
        Case("lsv validate", "option", ["lsv", "validate", "{model}", "{scan}", "--heldout", "0"], ("--heldout",)),
        Case(
            "simulate",
            "option",
            ["simulate", "--model", "{model}", "--out", "{case}/m.tif"],
            ("--volume", "--emitters"),
        ),
        Case(
            "simulate",
            "option",
            ["simulate", "--model", "{model}", "--emitters", "{emitters}", "--bit-depth", "9", "--out", "{case}/m.tif"],
            ("--bit-depth",),
        ),
        Case(
            "simulate",
            "option",
            ["simulate", "--model", "{model}", "--emitters", "{emitters}", "--out", "{case}/m.png"],
            ("--out",),
        ),
        Case(
            "simulate",
            "option",
            ["simulate", "--model", "{model}", "--volume", "{meas}", "--voxel-um", "1,2", "--out", "{case}/m.tif"],
            ("--voxel-um",),
        ),
        Case("synth", "option", ["synth", "--model", "{model}", "--size", "huge", "--out", "{case}/s"], ("--size",)),
        Case("synth", "option", ["synth", "--model", "{model}", "--fov-mm", "a,b", "--out", "{case}/s"], ("--fov-mm",)),
        Case(
            "synth",
            "option",
            ["synth", "--model", "{model}", "--density", "1,2,3", "--out", "{case}/s"],
            ("--density",),
        ),
        Case(
            "synth",
            "option",
            ["synth", "--model", "{model}", "--voxel-um", "0,1,1", "--out", "{case}/s"],
            ("--voxel-um",),
        ),
        Case("synth", "option", ["synth", "--model", "{model}", "-n", "0", "--out", "{case}/s"], ("--n-volumes",)),
        Case(
            "reconstruct",
            "option",
            [
                "reconstruct",
                "{meas}",
                "--model",
                "{model}",
                "--grid",
                "1,2",
                "--voxel-um",
                "1,1,1",
                "--out",
                "{case}/v.tif",
            ],
            ("--grid",),
        ),
        Case(
            "reconstruct",
            "option",
            ["reconstruct", "{meas}", "--model", "{model}", "--grid", "4,4,4", "--out", "{case}/v.tif"],
            ("--grid", "--voxel-um"),
        ),
        Case(
            "reconstruct",
            "option",
            ["reconstruct", "{meas}", "--model", "{model}", "--out", "{case}/v.png"],
            ("--out",),
        ),
        Case(
            "reconstruct",
            "option",
            ["reconstruct", "{meas}", "--model", "{model}", "--method", "magic", "--out", "{case}/v.tif"],
            ("magic",),
        ),
        Case("evaluate", "option", ["evaluate", "{meas}", "{emitters}", "--voxel-um", "1,x,1"], ("--voxel-um",)),
        Case("evaluate", "option", ["evaluate", "{meas}", "{emitters}", "--validation", "onlyone"], ("--validation",)),
        Case("spectra fit-filter", "option", ["spectra", "fit-filter", "{curves}", "--fit-aoi", "95"], ("--fit-aoi",)),
        Case(
            "spectra fit-filter",
            "option",
            ["spectra", "fit-filter", "{curves}", "--predict-aoi", "90"],
            ("--predict-aoi",),
        ),
        Case("cad export", "option", ["cad", "export", "--format", "obj", "--out", "{case}/o"], ("--format",)),
        Case(
            "cad export", "option", ["cad", "export", "--tolerance-um", "0", "--out", "{case}/o"], ("--tolerance-um",)
        ),
        Case("illum run", "option", ["illum", "run", "--rays", "10", "--out", "{case}/o"], ("--rays",)),
        Case(
            "illum run",
            "option",
            ["illum", "run", "--led-position", "1,2", "--collimator", "{garbage_stl}", "--out", "{case}/o"],
            ("--led-position",),
        ),
        Case("illum run", "option", ["illum", "run", "--led-axis", "0,0,1", "--out", "{case}/o"], ("--collimator",)),
        Case(
            "illum run",
            "option",
            ["illum", "run", "--rays", "1000", "--bin-mm", "0", "--out", "{case}/o"],
            ("--bin-mm",),
        ),
        Case("illum optimize", "option", ["illum", "optimize", "--max-cv", "2", "--out", "{case}/o"], ("--max-cv",)),
        Case("illum optimize", "option", ["illum", "optimize", "--samples", "1", "--out", "{case}/o"], ("--samples",)),
        Case(
            "illum optimize", "option", ["illum", "optimize", "--method", "newton", "--out", "{case}/o"], ("--method",)
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--method", "gradient", "--free-aim", "--out", "{case}/o"],
            ("--free-aim",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--method", "gradient", "--iterations", "1", "--out", "{case}/o"],
            ("--iterations",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--method", "gradient", "--step-rule", "newton", "--out", "{case}/o"],
            ("--step-rule",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--robust-samples", "-1", "--out", "{case}/o"],
            ("--robust-samples",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--method", "gradient", "--robust-samples", "4", "--out", "{case}/o"],
            ("--robust-samples",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--min-sbr-hybrid", "-1", "--out", "{case}/o"],
            ("--min-sbr-hybrid",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--method", "gradient", "--min-sbr-interference", "5", "--out", "{case}/o"],
            ("--min-sbr-interference",),
        ),
        Case(
            "illum optimize",
            "option",
            ["illum", "optimize", "--robust-samples", "4", "--unit-tilt-deg", "-1", "--out", "{case}/o"],
            ("unit_tilt_deg",),
        ),
        Case(
            "illum robustness", "option", ["illum", "robustness", "--samples", "1", "--out", "{case}/o"], ("--samples",)
        ),
        Case(
            "illum robustness",
            "option",
            ["illum", "robustness", "--surface-rms-um", "-1", "--out", "{case}/o"],
            ("surface_rms_um",),
        ),
        Case(
            "compare-baselines",
            "option",
            ["compare-baselines", "{model}", "{case}/o", "--runs", "{{not json"],
            ("--runs",),
        ),
        Case(
            "compare-baselines",
            "option",
            ["compare-baselines", "{model}", "{case}/o", "--n-volumes", "0"],
            ("--n-volumes",),
        ),
        # sizes: refused before anything is allocated
        Case(
            "lsv build",
            "size-guard",
            ["lsv", "build", "{scan}", "--lateral-um", "0.01", "--out", "{case}/m.h5"],
            ("--lateral-um",),
        ),
        Case(
            "lsv build",
            "size-guard",
            ["lsv", "build", "{scan}", "--patch-px", "100000", "--out", "{case}/m.h5"],
            ("--patch-px",),
        ),
        Case(
            "reconstruct",
            "size-guard",
            [
                "reconstruct",
                "{meas}",
                "--model",
                "{model}",
                "--grid",
                "200,20000,20000",
                "--voxel-um",
                "10,1,1",
                "--out",
                "{case}/v.tif",
            ],
            ("--max-memory-gib",),
        ),
        Case(
            "reconstruct",
            "size-guard",
            ["reconstruct", "{meas}", "--model", "{model}", "--max-memory-gib", "0.0000001", "--out", "{case}/v.tif"],
            ("--max-memory-gib",),
        ),
        # an unreachable Dask scheduler: refused at once, nothing left behind
        Case(
            "psf simulate",
            "dask",
            ["psf", "simulate", "--grid", "1x1x1", "--dask-address", "tcp://127.0.0.1:9", "--out", "{case}/o"],
            ("--dask-address",),
        ),
        Case(
            "synth",
            "dask",
            ["synth", "--model", "{model}", "--dask-address", "tcp://127.0.0.1:9", "--out", "{case}/s"],
            ("--dask-address",),
        ),
        Case(
            "illum optimize",
            "dask",
            ["illum", "optimize", "--dask-address", "tcp://127.0.0.1:9", "--out", "{case}/o"],
            ("--dask-address",),
        ),
        Case(
            "compare-baselines",
            "dask",
            ["compare-baselines", "{model}", "{case}/o", "--dask-address", "tcp://127.0.0.1:9"],
            ("--dask-address",),
        ),
        Case(
            "psf simulate",
            "dask",
            ["psf", "simulate", "--grid", "1x1x1", "--dask-address", "nonsense:", "--out", "{case}/o"],
            ("--dask-address",),
        ),
    ]


def _network_and_calibration_cases() -> list[Case]:
    """`cm2 net-testset` (weights: the repository's shipped folder), `cm2 train`, `cm2 calibrate scan`
    and `cm2 calibrate image` (a frame of the cm2-v2 sensor binned 16×)."""
    weights = str(SHIPPED_WEIGHTS)
    return [
        Case("net-testset", "output-is-input", ["net-testset", weights, weights], ("is the input",)),
        Case("net-testset", "output-is-input", ["net-testset", weights, weights + "/sub"], ("inside the input",)),
        Case(
            "net-testset",
            "existing-output",
            ["net-testset", weights, "{case}"],
            ("not empty", "--overwrite"),
            {"k": "x"},
        ),
        Case("net-testset", "output-under-file", ["net-testset", weights, "{regular}/o"], ("regular", "is a file")),
        Case("net-testset", "input-file", ["net-testset", "{missing}", "{case}/o"], ("missing.tif", "no such")),
        Case(
            "net-testset",
            "input-file",
            ["net-testset", "{case}/w", "{case}/o"],
            ("SHA256SUMS", "missing"),
            {"w/": "", "w/config.yaml": "channels: 8\n"},
        ),
        Case(
            "net-testset",
            "input-file",
            ["net-testset", weights, "{case}/o", "--traced", "--model", "{missing}"],
            ("--model", "no such file"),
        ),
        Case(
            "net-testset",
            "input-file",
            ["net-testset", weights, "{case}/o", "--imaging-model", "{missing}"],
            ("--imaging-model", "no such file"),
        ),
        Case(
            "net-testset",
            "option",
            ["net-testset", weights, "{case}/o", "--field-mm", "7"],
            ("--field-mm", "--model", "whole sensor"),
        ),
        Case("train", "input-file", ["train", "{missing}"], ("missing.tif", "no such")),
        Case("train", "input-file", ["train", "{garbage_yaml}"], ("garbage.yaml", "YAML")),
        Case("train", "option", ["train", "{garbage_yaml}", "--keep", "best"], ("--keep", "--export")),
        Case(
            "train", "option", ["train", "{garbage_yaml}", "--keep", "first", "--export", "{case}/w"], ("--keep first",)
        ),
        Case("calibrate scan", "input-file", ["calibrate", "scan", "{missing}", "--out", "{case}/r"], ("no such",)),
        Case("calibrate scan", "input-file", ["calibrate", "scan", "{root}", "--out", "{case}/r"], ("scan.yaml",)),
        Case(
            "calibrate scan", "output-is-input", ["calibrate", "scan", "{scan}", "--out", "{scan}"], ("is the input",)
        ),
        Case(
            "calibrate scan",
            "option",
            ["calibrate", "scan", "{scan}", "--preset", "nope", "--out", "{case}/r"],
            ("unknown preset",),
        ),
        *_illumination_calibration_cases(),
        *_calibrate_image_cases(),
    ]


def _illumination_calibration_cases() -> list[Case]:
    """`cm2 calibrate illumination` (a bad map file, pixel size, map too small, output, preset)
    and `cm2 calibrate paper` (a design without collimators, a bad option, an existing output)."""
    command = "calibrate illumination"

    def run(*args: str) -> list[str]:
        return ["calibrate", "illumination", *args]

    paper = ["calibrate", "paper", "--rays", "10000"]
    return [
        Case("calibrate paper", "option", [*paper, "--preset", "cm2-v1", "--out", "{case}/r"], ("collimators",)),
        Case("calibrate paper", "option", [*paper, "--preset", "nope", "--out", "{case}/r"], ("unknown preset",)),
        Case("calibrate paper", "option", [*paper[:2], "--rays", "5", "--out", "{case}/r"], ("--rays",)),
        Case(
            "calibrate paper", "existing-output", [*paper, "--out", "{case}"], ("not empty", "--overwrite"), {"k": "x"}
        ),
        Case(
            command, "input-file", run("{missing}", "--pixel-um", "20", "--out", "{case}/r"), ("missing.tif", "no such")
        ),
        Case(
            command,
            "input-file",
            run("{garbage_tif}", "--pixel-um", "20", "--out", "{case}/r"),
            ("garbage.tif", "TIFF"),
        ),
        Case(command, "input-file", run("{adir}", "--pixel-um", "20", "--out", "{case}/r"), ("adir.tif",)),
        Case(command, "option", run("{map}", "--pixel-um", "0", "--out", "{case}/r"), ("--pixel-um", "> 0")),
        Case(command, "option", run("{map}", "--pixel-um", "400", "--out", "{case}/r"), ("--pixel-um", "half a bin")),
        Case(command, "input-file", run("{map}", "--pixel-um", "10", "--out", "{case}/r"), ("covers 0 bins",)),
        Case(
            command,
            "option",
            run("{map}", "--pixel-um", "20", "--counts-per-electron", "0", "--out", "{case}/r"),
            ("--counts-per-electron",),
        ),
        Case(command, "option", run("{map}", "--pixel-um", "20", "--bin-mm", "9", "--out", "{case}/r"), ("--bin-mm",)),
        Case(
            command,
            "option",
            run("{map}", "--pixel-um", "20", "--polish-rays", "-1", "--out", "{case}/r"),
            ("--polish-rays", "≥ 0"),
        ),
        Case(
            command,
            "option",
            run("{map}", "--pixel-um", "20", "--preset", "nope", "--out", "{case}/r"),
            ("unknown preset",),
        ),
        Case(command, "output-is-input", run("{map}", "--pixel-um", "20", "--out", "{map}"), ("is the input",)),
        Case(
            command,
            "existing-output",
            run("{map}", "--pixel-um", "20", "--out", "{case}"),
            ("not empty", "--overwrite"),
            {"k": "x"},
        ),
    ]


def _calibrate_image_cases() -> list[Case]:
    """`cm2 calibrate image`: a frame or an emitter list that cannot be compared."""
    header = "x_um,y_um,z_um,diameter_um,intensity\n"

    def image(frame: str, emitters: str = "{emitters}", *extra: str) -> list[str]:
        return ["calibrate", "image", frame, "--emitters", emitters, *extra, "--out", "{case}/r"]

    return [
        Case("calibrate image", "input-file", image("{missing}"), ("missing.tif", "no such")),
        Case("calibrate image", "input-file", image("{nan_frame}"), ("nan.npy", "NaN")),
        Case("calibrate image", "input-file", image("{beads}", "{garbage_csv}"), ("garbage.csv",)),
        Case(
            "calibrate image",
            "input-file",
            image("{beads}", "{case}/e.csv"),
            ("e.csv", "missing diameter_um, intensity"),
            {"e.csv": "x_um,y_um,z_um\n0,0,0\n"},
        ),
        Case(
            "calibrate image",
            "input-file",
            image("{small_frame}"),
            ("wrong sensor size", "100 × 120"),
        ),
        Case(
            "calibrate image",
            "input-file",
            image("{beads}", "{case}/far.csv"),
            ("outside the design's field", "row 2"),
            {"far.csv": header + "0,0,0,10,1\n9000,0,0,10,1\n"},
        ),
        Case(
            "calibrate image",
            "input-file",
            image("{beads}", "{case}/deep.csv"),
            ("outside the design's field",),
            {"deep.csv": header + "0,0,2000,10,1\n"},
        ),
        Case(
            "calibrate image",
            "input-file",
            image("{beads}", "{emitters}", "--scan-report", "{root}"),
            ("calibration.json",),
        ),
        Case("calibrate image", "output-is-input", image("{beads}")[:-1] + ["{emitters}"], ("is the input",)),
    ]


CASES = _output_cases() + _input_cases() + _network_and_calibration_cases()


def _id(case: Case) -> str:
    return f"{case.command}|{case.kind}|{' '.join(case.args[-2:])}"


def catalogue_counts() -> dict[str, collections.Counter]:
    """Cases by command and by class (printed by ``python tests/cli/test_bad_inputs.py``)."""
    by_command, by_kind = collections.Counter(), collections.Counter()
    for case in CASES:
        by_command[case.command] += 1
        by_kind[case.kind] += 1
    return {"command": by_command, "class": by_kind}


def test_the_catalogue_is_large_and_covers_every_writing_command():
    assert len(CASES) >= 100
    commands = {c.command for c in CASES}
    for name in [
        *FOLDER_WRITERS,
        *FILE_WRITERS,
        "compare-baselines",
        "lsv validate",
        "spectra fit-filter",
        "net-testset",
        "calibrate illumination",
    ]:
        assert _command(name) in commands


@pytest.mark.parametrize("case", CASES, ids=_id)
def test_bad_input(case: Case, inputs, tmp_path, monkeypatch):
    for name, text in case.setup.items():
        path = tmp_path / name.rstrip("/")
        if name.endswith("/"):
            path.mkdir(parents=True, exist_ok=True)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
    values = {k: str(v) for k, v in inputs.items()} | {"case": str(tmp_path)}
    args = [a.format(**values) for a in case.args]
    if case.cwd:
        monkeypatch.chdir(tmp_path)
    watched = (inputs["root"], tmp_path, *([SHIPPED_WEIGHTS] if str(SHIPPED_WEIGHTS) in args else []))
    before = _tree(*watched)
    result = runner.invoke(app, args)
    output = result.output + (result.stderr if result.stderr_bytes is not None else "")
    assert result.exit_code == case.code, f"{args}: exit {result.exit_code}\n{output}"
    assert "Traceback" not in output and isinstance(result.exception, SystemExit | type(None)), output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    for text in case.expect:
        assert text in lines[0], f"{text!r} not in {lines[0]!r}"
    after = _tree(*watched)
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"an input or an earlier output changed, or debris was left: {changed}"


if __name__ == "__main__":  # the counts for the record
    counts = catalogue_counts()
    print(f"{len(CASES)} cases")
    for key, counter in counts.items():
        print(f"by {key}: " + ", ".join(f"{k} {v}" for k, v in sorted(counter.items())))
