"""Volumes (ImageJ TIFF, .npy) and emitter CSVs: round trips, centred coordinates, clear errors."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import tifffile

from cm2optics.formats.emitters import Emitters, read_emitters, write_emitters
from cm2optics.formats.volume import VolumeError, VolumeGrid, read_volume, write_volume


def test_tiff_round_trip_keeps_spacing_and_opens_as_imagej(tmp_path):
    volume = np.random.default_rng(0).random((4, 6, 8)).astype(np.float32)
    path = write_volume(tmp_path / "v.tif", volume, (10.0, 4.15, 4.15))
    data, grid = read_volume(path)
    np.testing.assert_array_equal(data, volume)
    assert grid.shape == (4, 6, 8)
    assert grid.voxel_um == pytest.approx((10.0, 4.15, 4.15), rel=1e-6)
    with tifffile.TiffFile(path) as tif:
        assert tif.is_imagej and tif.imagej_metadata["spacing"] == pytest.approx(10.0)


def test_npy_needs_spacing(tmp_path):
    np.save(tmp_path / "v.npy", np.zeros((2, 3, 4), np.float32))
    with pytest.raises(VolumeError, match="no voxel spacing"):
        read_volume(tmp_path / "v.npy")
    _, grid = read_volume(tmp_path / "v.npy", (5.0, 2.0, 2.0))
    assert grid.voxel_um == (5.0, 2.0, 2.0)


def test_centred_coordinates():
    grid = VolumeGrid((3, 4, 5), (10.0, 2.0, 1.0))
    np.testing.assert_allclose(grid.axis_um(2), [-2, -1, 0, 1, 2])
    np.testing.assert_allclose(grid.axis_um(1), [-3, -1, 1, 3])
    np.testing.assert_allclose(grid.axis_mm(0), [-0.01, 0, 0.01])
    assert VolumeGrid.from_dict(grid.to_dict()) == grid


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (np.full((2, 3, 3), np.nan, np.float32), "NaN or infinite"),
        (-np.ones((2, 3, 3), np.float32), "negative values"),
        (np.zeros((2, 2, 3, 3), np.float32), "must have 3 dimensions"),
    ],
)
def test_bad_volumes(tmp_path, data, message):
    np.save(tmp_path / "v.npy", data)
    with pytest.raises(VolumeError, match=message):
        read_volume(tmp_path / "v.npy", (1.0, 1.0, 1.0))


def test_missing_corrupt_and_unknown(tmp_path):
    with pytest.raises(VolumeError, match="no such volume file"):
        read_volume(tmp_path / "none.tif")
    (tmp_path / "bad.tif").write_bytes(b"junk")
    with pytest.raises(VolumeError, match="not a readable TIFF"):
        read_volume(tmp_path / "bad.tif")
    (tmp_path / "v.raw").write_bytes(b"")
    with pytest.raises(VolumeError, match="unknown volume format"):
        read_volume(tmp_path / "v.raw")
    with pytest.raises(VolumeError, match="voxel_um"):
        VolumeGrid((2, 2, 2), (1.0, 0.0, 1.0))


def test_emitters_round_trip_and_errors(tmp_path):
    emitters = Emitters(
        np.array([1.5, -2.0]),
        np.array([0.0, 3.0]),
        np.array([-10.0, 20.0]),
        np.array([10.0, 0.0]),
        np.array([1.0, 0.5]),
    )
    path = write_emitters(tmp_path / "e.csv", emitters)
    assert path.read_text().splitlines()[0] == "x_um,y_um,z_um,diameter_um,intensity"
    back = read_emitters(path)
    np.testing.assert_allclose(back.positions_mm(), emitters.positions_mm())
    assert len(back) == 2 and len(back.subset(np.array([1]))) == 1
    path.write_text("x_um,y_um,z_um,diameter_um,intensity\n1,2,3,nan,1\n")
    with pytest.raises(VolumeError, match="line 2: diameter_um = 'nan' is not finite"):
        read_emitters(path)
    path.write_text("x,y,z\n1,2,3\n")
    with pytest.raises(VolumeError, match="columns must be"):
        read_emitters(path)
    path.write_text("x_um,y_um,z_um,diameter_um,intensity\n1,2,3,4,-1\n")
    with pytest.raises(VolumeError, match="must be ≥ 0"):
        read_emitters(path)


@pytest.mark.parametrize("module", ["volume.py", "emitters.py"])
def test_volume_io_does_not_import_torch(module):
    source = (Path(__file__).resolve().parents[2] / "cm2optics" / "formats" / module).read_text()
    imported = {
        node.names[0].name.split(".")[0] for node in ast.walk(ast.parse(source)) if isinstance(node, ast.Import)
    }
    imported |= {
        node.module.split(".")[0]
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.ImportFrom) and node.module
    }
    assert "torch" not in imported
