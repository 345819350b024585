"""Synthetic data sets: views at the chief rays, demixed views, patches aligned with their
volumes, files and manifest, the same data for the same seed (in-process and on Dask), the
`cm2 synth` command, and the LSV model as the forward model."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from cm2optics.formats.emitters import Emitters
from cm2optics.lsv.toy import gaussian_lsi_operator
from cm2optics.synth.config import SynthConfig
from cm2optics.synth.dataset import make_dataset, read_sample
from cm2optics.synth.generate import synthesize_sample
from cm2optics.synth.imaging import Imaging
from cm2optics.synth.views import crop_views, volume_patch

CONFIG = SynthConfig.scaled(
    20, voxel_um=(40.0, 8.0, 8.0), view_px=64, patch_px=32, patches_per_volume=3, density_per_mm2=(40.0, 100.0)
)


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Small tensors: one intra-op thread is faster, and far faster on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def toy(config: SynthConfig = CONFIG):
    return gaussian_lsi_operator(config.grid, (160, 160), defocus_px_per_um=0.006)


@pytest.fixture(scope="module")
def toy_file(tmp_path_factory):
    return toy().save(tmp_path_factory.mktemp("model") / "toy.h5")


def test_a_sample_has_every_part():
    sample = synthesize_sample(CONFIG, Imaging(toy(), CONFIG.grid), 0, 1, keep_clean=True)
    J = 9
    assert sample.measurement.shape == (160, 160) and sample.views.shape == (J, 64, 64)
    assert sample.demixed.shape == (J, 64, 64) and sample.volume.shape == CONFIG.grid.shape
    assert sample.clean.max() == pytest.approx(1.0)
    assert sample.patches["views"].shape == (3, J, 32, 32) and sample.patches["volume"].shape == (3, 21, 32, 32)
    # the demixed images sum to the clean measurement
    op = toy()
    per_lenslet = op.forward(sample.volume, per_lenslet=True) / sample.image_scale
    np.testing.assert_allclose(per_lenslet.sum(0), sample.clean, atol=1e-5)
    np.testing.assert_allclose(sample.demixed, crop_views(per_lenslet, op.chief_rays_px(), 64), atol=1e-5)


def test_views_are_cropped_at_the_chief_rays_and_patches_match_their_volume():
    config = CONFIG.with_changes(noise="none")
    op = toy(config)
    grid = config.grid
    # one emitter at the focal plane, off the centre: the nine views see it at the same pixel
    ix, iy = 30, 15
    x, y = grid.axis_um(2)[ix], grid.axis_um(1)[iy]
    emitter = Emitters([x], [y], [grid.axis_um(0)[10]], [12.0], [1.0])
    from cm2optics.synth.raster import rasterize_balls

    volume = rasterize_balls(emitter, grid)
    image = op.forward(volume)
    views = crop_views(image, op.chief_rays_px(), 64)
    peaks = np.array([np.unravel_index(np.argmax(v), v.shape) for v in views])
    assert np.ptp(peaks, axis=0).max() <= 1  # chief rays rounded to whole pixels
    row, col = (int(v) for v in np.median(peaks, axis=0).round())
    # inverted image: +x lands left of the view centre, +y above it
    assert col < 32 and row > 32 - 1
    # the patch that holds the peak holds the emitter in its volume, at the same place
    origin = np.array([row - 10, col - 12])
    block, _ = volume_patch(volume, origin, 64, 32, np.array([-1.0, -1.0]))
    peak_voxel = np.unravel_index(np.argmax(block.max(0)), block.shape[1:])
    assert abs(peak_voxel[0] - 10) <= 1 and abs(peak_voxel[1] - 12) <= 1


def _hashes(folder):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((folder / "samples").glob("*.h5"))}


def test_dataset_files_manifest_and_reproducibility(toy_file, tmp_path):
    a = make_dataset(CONFIG, toy_file, tmp_path / "a", 3, seed=11, workers=0)
    b = make_dataset(CONFIG, toy_file, tmp_path / "b", 3, seed=11, workers=0)
    c = make_dataset(CONFIG, toy_file, tmp_path / "c", 2, seed=12, workers=0)
    assert [s["content_sha256"] for s in a["samples"]] == [s["content_sha256"] for s in b["samples"]]
    assert _hashes(tmp_path / "a") == _hashes(tmp_path / "b")  # byte-identical files
    assert a["samples"][0]["content_sha256"] != c["samples"][0]["content_sha256"]
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    for key in ("config", "seed", "model", "samples", "seconds", "grid", "n_patches", "cm2optics_version"):
        assert key in manifest
    assert manifest["model"]["sha256"] and manifest["n_patches"] == 9
    sample = read_sample(tmp_path / "a" / "samples" / "sample_00001.h5")
    assert sample["index"] == 1 and len(sample["emitters"]) == a["samples"][1]["n_emitters"]
    assert set(sample["patches"]) == {"views", "demixed", "volume", "origin", "voxel_origin"}
    import h5py

    with h5py.File(tmp_path / "a" / "dataset.h5", "r") as f:
        assert f["patch_index"].shape == (9, 2)
        assert f["samples/sample_00002/measurement"].shape == (160, 160)  # external links resolve
    assert not list((tmp_path / "a" / "samples").glob(".*tmp*"))


def test_rerun_into_a_folder_refuses_other_inputs_and_samples_are_verified(toy_file, tmp_path):
    from cm2optics.synth.dataset import DatasetError

    first = make_dataset(CONFIG, toy_file, tmp_path / "a", 2, seed=3, workers=0)
    again = make_dataset(CONFIG, toy_file, tmp_path / "a", 2, seed=3, workers=0)  # same inputs: a resume
    assert [s["content_sha256"] for s in first["samples"]] == [s["content_sha256"] for s in again["samples"]]
    with pytest.raises(DatasetError, match=r"another seed \(3 there, 4 now\)"):
        make_dataset(CONFIG, toy_file, tmp_path / "a", 2, seed=4, workers=0)
    other = SynthConfig.from_dict(CONFIG.to_dict() | {"noise": "none"})
    with pytest.raises(DatasetError, match=r"another config \(noise\)"):
        make_dataset(other, toy_file, tmp_path / "a", 2, seed=3, workers=0)
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["seed"] == 3
    import h5py

    path = tmp_path / "a" / "samples" / "sample_00001.h5"
    with h5py.File(path, "r+") as f:
        f["measurement"][0, 0] += 1.0
    with pytest.raises(DatasetError, match=r"sample_00001.h5: content_sha256 does not match"):
        read_sample(path)
    assert read_sample(path, verify=False)["index"] == 1


def test_dask_workers_make_the_same_data(toy_file, tmp_path):
    serial = make_dataset(CONFIG, toy_file, tmp_path / "serial", 2, seed=5, workers=0)
    parallel = make_dataset(CONFIG, toy_file, tmp_path / "dask", 2, seed=5, workers=2)
    assert [s["content_sha256"] for s in serial["samples"]] == [s["content_sha256"] for s in parallel["samples"]]
    assert parallel["workers"] == "local cluster × 2"


def _app():
    from cm2optics.cli.synth import synth_command

    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """test app"""

    app.command("synth")(synth_command)
    return app


def test_cli_synth_json_and_export(toy_file, tmp_path):
    result = CliRunner().invoke(
        _app(),
        [
            "synth",
            "--model",
            str(toy_file),
            "--out",
            str(tmp_path / "set"),
            "-n",
            "2",
            "--size",
            "scaled",
            "--scale",
            "20",
            "--view-px",
            "64",
            "--patch-px",
            "32",
            "--patches",
            "2",
            "--density",
            "40,100",
            "--workers",
            "0",
            "--export",
            "1",
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["n_volumes"] == 2 and len(data["samples"]) == 2 and data["n_patches"] == 4
    assert data["config"]["voxel_um"] == [40.0, 8.0, 8.0]  # taken from the model's grid
    exported = data["exported"][0]
    from cm2optics.formats.emitters import read_emitters
    from cm2optics.formats.volume import read_volume

    assert len(read_emitters(exported["emitters"])) == data["samples"][0]["n_emitters"]
    volume, grid = read_volume(exported["volume"])
    assert grid.shape == CONFIG.grid.shape and grid.voxel_um == pytest.approx((40.0, 8.0, 8.0), rel=1e-5)


def _one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    return lines[0]


def test_cli_synth_errors_are_one_line(toy_file, tmp_path):
    runner = CliRunner()
    line = _one_line_error(
        runner.invoke(_app(), ["synth", "--model", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "set")])
    )
    assert "no such model file" in line
    bad = tmp_path / "bad.h5"
    bad.write_text("not hdf5")
    assert "not an HDF5 model" in _one_line_error(
        runner.invoke(_app(), ["synth", "--model", str(bad), "--out", str(tmp_path / "set")])
    )
    line = _one_line_error(
        runner.invoke(
            _app(),
            ["synth", "--model", str(toy_file), "--out", str(tmp_path / "set"), "--noise", "loud", "--workers", "0"],
        )
    )
    assert "noise" in line
    # a PSF stack is defined on its own grid: a different field is refused with the reason
    line = _one_line_error(
        runner.invoke(_app(), ["synth", "--model", str(toy_file), "--out", str(tmp_path / "set"), "--workers", "0"])
    )
    assert "grid" in line


# ----------------------------------------------------------------------------- the LSV model


@pytest.fixture(scope="module")
def lsv_model(tmp_path_factory):
    """A small LSV model (analytic PSF scan binned 8×, 1.2-mm lateral step), built once per session."""
    from cm2optics.design import load_preset
    from cm2optics.lsv.model import load_model
    from cm2optics.lsv.toy import analytic_lsv_model_file

    path = tmp_path_factory.getbasetemp() / "shared-lsv-b8.h5"
    analytic_lsv_model_file(path, load_preset("cm2-v2"), binning=8, rank=6, lateral_nodes=7, depth_nodes=3)
    model = load_model(path)
    return model, path


def test_lsv_model_synthesis_sparse_and_volume(lsv_model):
    model, _ = lsv_model
    config = SynthConfig.scaled(
        2,
        voxel_um=model.default_grid.voxel_um,
        view_px=120,
        patch_px=40,
        patches_per_volume=2,
        density_per_mm2=(5.0, 10.0),
    )
    sparse = synthesize_sample(config, Imaging(model, config.grid, "sparse"), 0, 3, keep_clean=True)
    dense = synthesize_sample(config, Imaging(model, config.grid, "volume"), 0, 3, keep_clean=True)
    assert sparse.measurement.shape == model.sensor_shape
    # the two renderers agree on where the light goes (they differ in sub-pixel detail)
    a, b = sparse.clean * sparse.image_scale, dense.clean * dense.image_scale
    assert a.sum() == pytest.approx(b.sum(), rel=0.05)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.6
    rays = Imaging(model, config.grid).chief_rays_px()
    np.testing.assert_allclose(rays, model.geometry.focus(0.0, 0.0, 0.0))
    assert sparse.patches["volume"].shape[1:] == (config.grid.shape[0], 40, 40)
