"""`cm2 lsv build`, `cm2 lsv validate` and `cm2 simulate`: JSON keys, files, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile
import typer
import yaml
from typer.testing import CliRunner

from cm2optics.cli.lsv import lsv_app, simulate_command
from cm2optics.formats.emitters import Emitters, write_emitters
from cm2optics.formats.volume import write_volume
from cm2optics.lsv.model import load_model
from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan
from cm2optics.reports.lsv import FIGURES

app = typer.Typer()
app.add_typer(lsv_app, name="lsv")
app.command("simulate")(simulate_command)
runner = CliRunner()


@app.callback()
def _root() -> None:
    """Test root: a group, so that `lsv` and `simulate` are subcommands as under `cm2`."""


@pytest.fixture(scope="module")
def scan(v2, tmp_path_factory) -> Path:
    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=19.2)
    axis = np.linspace(-3, 3, 5)
    return write_analytic_scan(
        tmp_path_factory.mktemp("cli") / "scan", analytic, axis, axis, np.linspace(-0.3, 0.3, 5), binning=8
    )


@pytest.fixture(scope="module")
def model(scan) -> tuple[Path, dict]:
    out = scan.parent / "model.h5"
    result = runner.invoke(app, ["lsv", "build", str(scan), "--rank", "16", "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    return out, json.loads(result.stdout)


def test_build_json_model_and_report(model):
    path, summary = model
    assert path.is_file()
    assert summary["rank"] == 16
    assert 0 <= summary["nmse_calibration"] < 0.05
    assert set(summary["nmse_vs_rank"]) >= {"1", "4", "8", "16"}
    # a flat field whose 1-px foci hardly change over ±0.3 mm: no measurable best focus, so no
    # focal surface (the build says why) and plain interpolation
    assert "no focal surface" in summary["focal_surface"]["fallback"]
    assert load_model(path).focal_surface is None
    # the turn with the azimuth: decided by nodes left out, both errors and the choice recorded
    rotation = summary["rotation"]
    check = rotation["leave_one_out"]
    assert check["n_heldout"] > 0 and check["nmse_fixed_orientation"] >= 0 and check["nmse_turned"] >= 0
    assert rotation["turned"] == (check["nmse_turned"] < 0.9 * check["nmse_fixed_orientation"])
    assert load_model(path).rotate_aberrations == rotation["turned"]
    plain, warped = ("turned", "turned_warped") if rotation["turned"] else ("fixed_orientation", "warped")
    assert rotation["warped"] == (check[f"nmse_{warped}"] < 0.9 * check[f"nmse_{plain}"])
    assert load_model(path).warp_shapes == rotation["warped"]
    report = Path(summary["report"])
    assert report.name == "report.html" and report.is_file()
    for name in FIGURES:
        assert (report.parent / name).stat().st_size > 1000


def test_build_a_per_lenslet_basis(scan, tmp_path):
    out = tmp_path / "per_lenslet.h5"
    arguments = ["lsv", "build", str(scan), "--rank", "4", "--per-lenslet-basis", "--no-report", "--json"]
    result = runner.invoke(app, arguments + ["--rotate", "off", "--warp", "off", "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary, model = json.loads(result.stdout), load_model(out)
    assert summary["rank"] == model.rank == 9 * 4 and model.provenance["svd"]["basis"].startswith("per lenslet")
    assert all(len(model.lenslet_terms(j)) == 4 for j in range(9))
    assert 0 <= summary["nmse_calibration"] < 0.05
    image = model.point_image(0.5, -0.7, 0.1)
    assert image.sum() > 0 and np.isfinite(image).all()
    with pytest.warns(UserWarning, match="per-lenslet basis"):  # validate's check is of another structure: said so
        result = runner.invoke(
            app, ["lsv", "validate", str(out), str(scan), "--json", "--no-subsample", "--heldout", "4", "--refit"]
        )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert "one basis of focus arrays" in data["basis_warning"]
    # --refit: the model's own structure, its basis decomposed per lenslet without the held-out nodes
    leave_out = data["leave_out"]
    assert leave_out["basis"] == "per lenslet, 4 terms each" and leave_out["n_heldout"] == 4
    assert 0 <= leave_out["nmse"] < 1 and leave_out["nmse_median"] >= 0 and leave_out["nmse_full"] >= 0


def test_validate_json_on_the_calibration_scan(model, scan):
    path, _ = model
    result = runner.invoke(
        app, ["lsv", "validate", str(path), str(scan), "--json", "--heldout", "6", "--ranks", "4,16"]
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["method"] == "leave-one-out" and data["n_heldout"] == 6
    assert 0 < data["nmse_heldout"] < 0.5
    assert set(data["nmse_heldout_vs_rank"]) == {"4", "16"}
    assert set(data["nmse_subsampled"]) == {"lateral_2x", "axial_2x"}
    with pytest.warns(UserWarning) as record:
        result = runner.invoke(
            app,
            [
                "lsv",
                "validate",
                str(path),
                str(scan),
                "--json",
                "--heldout",
                "999",
                "--ranks",
                "4,999",
                "--no-subsample",
            ],
        )
    assert result.exit_code == 0, result.output
    messages = " | ".join(str(w.message) for w in record)
    assert "--heldout 999: the scan has only" in messages and "--ranks: 999 exceed" in messages
    assert json.loads(result.stdout)["n_heldout"] < 999


def test_validate_on_a_second_offset_scan(model, v2, tmp_path):
    path, _ = model
    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=19.2)
    offset = write_analytic_scan(
        tmp_path / "offset",
        analytic,
        np.array([-0.75, 0.75]),
        np.array([-0.75, 0.75]),
        np.array([-0.15, 0.15]),
        binning=8,
        seed=3,
    )
    result = runner.invoke(app, ["lsv", "validate", str(path), str(offset), "--json", "--no-subsample"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["method"] == "second scan" and data["n_heldout"] == 8
    assert 0 < data["nmse_heldout"] < 0.2
    assert data["brightness_ratio"] == pytest.approx(1.0, abs=0.15)


def test_simulate_emitters_with_noise(model, tmp_path):
    path, _ = model
    csv = write_emitters(
        tmp_path / "e.csv",
        Emitters(
            np.array([0.0, 800.0]),
            np.array([0.0, -400.0]),
            np.array([0.0, 100.0]),
            np.array([10.0, 15.0]),
            np.array([1.0, 2.0]),
        ),
    )
    out = tmp_path / "meas.tif"
    result = runner.invoke(
        app,
        [
            "simulate",
            "--model",
            str(path),
            "--emitters",
            str(csv),
            "--noise",
            "--seed",
            "1",
            "--out",
            str(out),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    counts = tifffile.imread(out)
    assert counts.dtype == np.uint16 and counts.shape == (259, 386)
    sidecar = yaml.safe_load(out.with_suffix(".yaml").read_text())
    assert sidecar["noise"]["poisson_peak_photons"] == 500 and sidecar["bit_depth"] == 12
    assert 0.03 * 4095 < np.median(counts) < 0.07 * 4095  # the dark offset
    assert sidecar["dark_level"] == pytest.approx(0.048 * 4095, abs=0.01) and sidecar["counts_per_unit"] > 0
    again = tmp_path / "again.tif"
    runner.invoke(
        app, ["simulate", "--model", str(path), "--emitters", str(csv), "--noise", "--seed", "1", "--out", str(again)]
    )
    np.testing.assert_array_equal(tifffile.imread(again), counts)


def test_simulate_warns_about_emitters_outside_the_calibration(model, tmp_path):
    path, _ = model
    far = Emitters(*(np.array(v) for v in ([0.0, 0.0], [0.0, 0.0], [0.0, 3000.0], [10.0, 10.0], [1.0, 1.0])))
    csv = write_emitters(tmp_path / "far.csv", far)
    with pytest.warns(
        UserWarning, match=r"1 of 2 emitters lie outside the model's calibrated range \(x -3…3, y -3…3, z -0.3…0.3 mm\)"
    ):
        result = runner.invoke(
            app, ["simulate", "--model", str(path), "--emitters", str(csv), "--out", str(tmp_path / "m.tif")]
        )
    assert result.exit_code == 0, result.output


def test_simulate_emitters_placed_exactly(model, tmp_path):
    """--subpixel-steps 0 places every emitter at its exact sub-pixel position: the written image
    is the model's exact sparse image (to the 12-bit counts)."""
    from cm2optics.lsv.model import load_model

    path, _ = model
    emitters = Emitters(np.array([730.0]), np.array([-410.0]), np.array([37.0]), np.array([2.0]), np.array([1.0]))
    csv = write_emitters(tmp_path / "e.csv", emitters)
    out = tmp_path / "exact.tif"
    result = runner.invoke(
        app, ["simulate", "--model", str(path), "--emitters", str(csv), "--subpixel-steps", "0", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    sidecar = yaml.safe_load(out.with_suffix(".yaml").read_text())
    assert sidecar["source"]["subpixel_steps"] == "exact"
    exact = load_model(path).forward_sparse(emitters, subpixel_steps=None).astype(np.float64)
    written = tifffile.imread(out) / sidecar["counts_per_unit"]
    assert np.abs(written - np.clip(exact, 0, None)).max() <= 0.51 / sidecar["counts_per_unit"]


def test_simulate_volume_per_lenslet_and_lsi(model, tmp_path):
    path, summary = model
    voxel = summary["default_grid"]["voxel_um"]
    volume = np.zeros((5, 30, 30), np.float32)
    volume[2, 15, 15] = 1.0
    write_volume(tmp_path / "v.tif", volume, tuple(voxel))
    out = tmp_path / "views.tif"
    result = runner.invoke(
        app, ["simulate", "--model", str(path), "--volume", str(tmp_path / "v.tif"), "--per-lenslet", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert tifffile.imread(out).shape == (9, 259, 386)
    np.save(tmp_path / "v.npy", volume)
    result = runner.invoke(
        app,
        [
            "simulate",
            "--model",
            str(path),
            "--volume",
            str(tmp_path / "v.npy"),
            "--lsi",
            "--out",
            str(tmp_path / "lsi.tif"),
        ],
    )
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["lsv", "build", "/no/such/scan"], "no such scan folder"),
        (["lsv", "build", "{scan}", "--rank", "0"], "--rank = 0"),
        (["lsv", "build", "{scan}", "--refine", "0"], "--refine = 0"),
        (["lsv", "build", "{scan}", "--rotate", "sideways"], "--rotate = 'sideways'"),
        (["lsv", "build", "{scan}", "--rotate", "on", "--refine", "1"], "--rotate on needs --refine ≥ 2"),
        (["lsv", "build", "{scan}", "--warp", "maybe"], "--warp = 'maybe'"),
        (["lsv", "build", "{scan}", "--warp", "on", "--refine", "1"], "--warp on needs --refine ≥ 2"),
        (["lsv", "build", "{scan}", "--memory-gb", "0"], "--memory-gb = 0.0: must be > 0"),
        (["lsv", "build", "{scan}", "--aberration-model", "-1"], "--aberration-model = -1: must be ≥ 0"),
        (["lsv", "build", "{scan}", "--aberration-model", "100"], "--aberration-model needs an ePSF basis"),
        (["lsv", "build", "{scan}", "--node-coefficients", "crops"], "--node-coefficients = 'crops': must be"),
        (
            ["lsv", "build", "{scan}", "--node-coefficients", "scan"],
            "--node-coefficients scan needs --aberration-model",
        ),
        (["lsv", "validate", "/no/model.h5", "{scan}"], "no such model file"),
        (["lsv", "validate", "{model}", "{scan}", "--ranks", "a,b"], "--ranks"),
        (["lsv", "validate", "{model}", "{scan}", "--refit", "--memory-gb", "0"], "--memory-gb = 0.0: must be > 0"),
        (["simulate", "--model", "{model}", "--out", "x.tif"], "exactly one of --volume and --emitters"),
        (["simulate", "--model", "{model}", "--emitters", "/no/e.csv", "--out", "x.tif"], "no such emitter file"),
        (["simulate", "--model", "{model}", "--volume", "{scan}/scan.yaml", "--out", "x.tif"], "unknown volume format"),
        (
            [
                "simulate",
                "--model",
                "{model}",
                "--emitters",
                "{scan}/e.csv",
                "--subpixel-steps",
                "99",
                "--out",
                "x.tif",
            ],
            "--subpixel-steps = 99",
        ),
    ],
)
def test_user_errors_are_one_line(model, scan, arguments, message):
    path, _ = model
    arguments = [a.format(scan=scan, model=path) for a in arguments]
    result = runner.invoke(app, arguments)
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output


def test_demo_lsv_section_checks_the_model_between_its_nodes(v2, scan, tmp_path):
    """The demo's chain section: the model built from a scan, scored against points between the
    nodes; a reference that is the model itself scores 0, a scaled one exactly its scale error."""
    from cm2optics.lsv.model import load_model
    from cm2optics.reports.document import Report
    from cm2optics.reports.lsv import add_lsv_section, heldout_positions

    report = Report("t")
    calls = []

    def traced(position):
        calls.append(position)
        built = load_model(tmp_path / "lsv" / "model.h5")
        return 1.25 * built.point_image(*position)

    numbers = add_lsv_section(report, v2, scan, tmp_path, rank=16, traced=traced)
    errors = numbers["heldout_error"]["oversample 1 (this model)"]
    assert len(errors) == len(calls) == 4
    np.testing.assert_allclose(errors, 0.2, atol=1e-9)  # ‖m − 1.25 m‖ / ‖1.25 m‖
    model = load_model(tmp_path / "lsv" / "model.h5")
    xs, ys, zs = model.axes
    for x, y, z in heldout_positions(model):
        assert zs[0] < z < zs[-1] and xs[0] < x < xs[-1] and ys[0] < y < ys[-1]
        assert not (np.isclose(xs, x).any() and np.isclose(ys, y).any() and np.isclose(zs, z).any())
    assert "Between the nodes" in report.to_markdown()
