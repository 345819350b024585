"""Synthetic PSF scans and measurements: positions, the scan format, resuming, the `cm2 psf` commands."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile
import yaml
from typer.testing import CliRunner

import cm2optics.emission.scan as scan_module
from cm2optics.cli.options import parse_int_list
from cm2optics.cli.psf import psf_app
from cm2optics.emission.image import render_emitters
from cm2optics.emission.psf import EmissionModel, PSFSettings, SensorGrid
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, read_positions_csv, simulate_scan
from cm2optics.emission.source import fluorescent_bead
from cm2optics.formats.emitters import Emitters, read_emitters
from cm2optics.formats.scan import read_scan
from cm2optics.optics import first_order

runner = CliRunner()
FAST = ScanSettings(psf=PSFSettings(binning=8), source=fluorescent_bead(5.0))


def test_the_papers_calibration_grid(v2):
    positions = calibration_grid_mm(v2, (9, 9, 11))
    assert positions.shape == (891, 3)
    xs, ys, zs = (np.unique(positions[:, k]) for k in range(3))
    assert np.allclose(xs, np.arange(-4, 4.01, 1.0)) and np.allclose(ys, xs)
    assert np.allclose(zs, np.arange(-0.5, 0.51, 0.1))
    assert np.allclose(positions[:9, 0], xs)  # x runs fastest, z slowest
    assert np.allclose(calibration_grid_mm(v2, (1, 1, 1)), 0.0)
    # z = 0 is the best focus; the paraxial conjugate lies beyond the calibrated depth.
    assert first_order.object_z_to_height_mm(v2, 0.0) == first_order.object_plane_z_mm(v2)
    assert -first_order.focus_shift_mm(v2) < zs.min()


def test_scan_metadata_names_the_focal_plane(v2):
    meta = scan_module._extra_meta(v2, FAST, SensorGrid.of(v2, 8))
    assert "best focus" in meta["position_units"] and "best focus" in meta["focal_plane"]
    assert meta["focal_plane_height_mm"] == pytest.approx(first_order.object_plane_z_mm(v2), abs=1e-6)
    assert meta["paraxial_focal_plane_z_mm"] == pytest.approx(-first_order.focus_shift_mm(v2), abs=1e-6)
    assert meta["object_pixel_um"] == pytest.approx(4.15, rel=0.01)


def test_bad_chunk_sizes_are_refused(v2, tmp_path):
    with pytest.raises(ValueError, match="chunk_size"):
        simulate_scan(v2, np.zeros((1, 3)), tmp_path / "s", FAST, chunk_size=0, progress=False)


@pytest.mark.parametrize("text", ["9x9", "0x9x11", "axbxc", "9x9x200"])
def test_bad_grids_are_refused(text):
    with pytest.raises(ValueError, match="--grid"):
        parse_int_list(text, 3, name="--grid", sep="x", low=1, high=101)


def test_positions_csv(tmp_path):
    good = tmp_path / "good.csv"
    good.write_text("# a line of sources\nx_mm,y_mm,z_mm,comment\n0,0,-0.1,a\n0,0,0.1,b\n")
    assert np.allclose(read_positions_csv(good), [[0, 0, -0.1], [0, 0, 0.1]])
    missing = tmp_path / "missing.csv"
    missing.write_text("x_mm,y_mm\n0,0\n")
    with pytest.raises(ValueError, match="z_mm"):
        read_positions_csv(missing)
    nan = tmp_path / "nan.csv"
    nan.write_text("x_mm,y_mm,z_mm\n0,0,nan\n")
    with pytest.raises(ValueError, match="finite"):
        read_positions_csv(nan)
    scattered = tmp_path / "scattered.csv"
    scattered.write_text("x_mm,y_mm,z_mm\n0,0,0\n1,1,0\n")
    with pytest.raises(ValueError, match="grid"):
        read_positions_csv(scattered)
    with pytest.raises(FileNotFoundError):
        read_positions_csv(tmp_path / "nope.csv")


def test_a_source_inside_the_device_is_refused(v2):
    model = EmissionModel(v2, settings=PSFSettings(binning=8))
    with pytest.raises(ValueError, match="z_mm"):
        model.foci((0.0, 0.0, 9.0))
    with pytest.raises(ValueError, match="position_mm"):
        model.foci((0.0, np.nan, 0.0))


def test_scan_writes_the_measured_format_and_resumes(v2, tmp_path, monkeypatch):
    positions = calibration_grid_mm(v2, (3, 1, 2), field_mm=2.0)
    out = tmp_path / "scan"
    original = scan_module._simulate_chunk
    calls = []

    def failing(design, settings, key, items, threads=None):
        calls.extend(i for i, _ in items)
        if any(i == 4 for i, _ in items):
            raise RuntimeError("power cut")
        return original(design, settings, key, items, threads)

    monkeypatch.setattr(scan_module, "_simulate_chunk", failing)
    with pytest.raises(RuntimeError, match="power cut"):
        simulate_scan(v2, positions, out, FAST, workers=1, processes=False, chunk_size=1, progress=False)
    work = scan_module._work_folder(out)
    kept = sorted(work.glob("pos_*.npz"))
    assert kept and not out.exists()  # finished positions kept; no half-written scan

    monkeypatch.setattr(scan_module, "_simulate_chunk", original)
    resumed = []
    manifest = simulate_scan(
        v2,
        positions,
        out,
        FAST,
        workers=1,
        processes=False,
        chunk_size=1,
        progress=False,
        on_position=lambda done, total: resumed.append(done),
    )
    assert resumed[0] == len(kept) + 1  # it started where the first run stopped
    assert not work.exists()
    scan = read_scan(out)
    assert scan.images.shape[0] == 6 and np.allclose(scan.positions_mm, positions)
    assert scan.meta.extra["synthetic"] is True
    peak = (scan.images.astype(float) - scan.meta.dark_level).max(axis=(1, 2))
    assert np.allclose(peak, FAST.fill * (2**scan.meta.bit_depth - 1), rtol=0.01)  # adaptive exposure
    assert manifest["inputs"]["positions"] == 6
    # Counts per ms are proportional to the PSF: the on-axis source (index 1) outshines its neighbours.
    norm = scan.normalised()
    assert norm[1].sum() > norm[0].sum()


def test_cli_simulate_writes_a_scan(v2, tmp_path):
    from dask.distributed import LocalCluster

    positions = tmp_path / "pos.csv"
    positions.write_text("x_mm,y_mm,z_mm\n0,0,0\n0.5,0,0\n")
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        result = runner.invoke(
            psf_app,
            [
                "simulate",
                "--positions",
                str(positions),
                "--binning",
                "8",
                "--out",
                str(tmp_path / "s"),
                "--dask-address",
                cluster.scheduler_address,
                "--profile",
                "isotropic",
                "--json",
            ],
        )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["inputs"]["positions"] == 2
    scan = read_scan(tmp_path / "s")
    assert scan.meta.pixel_um == pytest.approx(8 * v2.sensor.pixel_um)
    assert "source_profile: isotropic" in (tmp_path / "s" / "scan.yaml").read_text()


@pytest.mark.parametrize(
    "args, message",
    [
        (["simulate", "--grid", "9x9"], "--grid"),
        (["simulate", "--grid", "3x3x3", "--positions", "p.csv"], "not both"),
        (["simulate", "--positions", "nope.csv"], "nope.csv"),
        (["simulate", "--grid", "1x1x1", "--binning", "0"], "binning"),
        (["simulate", "--grid", "1x1x1", "--profile", "conical"], "--profile"),
        (["simulate", "--preset", "cm2-v9", "--grid", "1x1x1"], "preset"),
        (["image", "--emitters", "nope.csv"], "nope.csv"),
    ],
)
def test_cli_user_errors_end_in_one_line(args, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(psf_app, args)
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


def test_emitters_csv_and_cli_image(v2, tmp_path):
    path = tmp_path / "emitters.csv"
    path.write_text("x_um,y_um,z_um,diameter_um,intensity\n0,0,0,10,1\n300,-200,100,15,0.5\n")
    emitters = read_emitters(path)
    assert len(emitters) == 2 and emitters.diameter_um[1] == 15
    out = tmp_path / "m.tif"
    result = runner.invoke(psf_app, ["image", "--emitters", str(path), "--binning", "8", "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    image = tifffile.imread(out)
    assert image.dtype == np.uint16 and image.max() > 0
    sidecar = yaml.safe_load(out.with_suffix(".yaml").read_text())
    assert sidecar["pixel_um"] == pytest.approx(8 * v2.sensor.pixel_um) and sidecar["counts_per_unit"] > 0
    bad = tmp_path / "bad.csv"
    bad.write_text("x_um,y_um,z_um,diameter_um,intensity\n0,0,0,10,-1\n")
    with pytest.raises(ValueError, match="intensity"):
        read_emitters(bad)
    with pytest.raises(ValueError, match="diameter_um"):
        render_emitters(v2, Emitters.from_positions_um(np.zeros((1, 3)), np.array([500.0]), np.array([1.0])))
