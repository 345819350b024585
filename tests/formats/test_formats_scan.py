"""The PSF scan format: round trip, lazy reading, and one clear error for every broken folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml

from cm2optics.formats.scan import (
    PSFScan,
    ScanError,
    ScanIndex,
    ScanMeta,
    grid_axes_mm,
    grid_index,
    open_scan,
    read_scan,
    write_scan,
)

META = ScanMeta(pixel_um=2.4, binning=1, bit_depth=12, dark_level=100.0, extra={"lenslets": [3, 3]})


def _grid_positions() -> np.ndarray:
    return np.array([[x, y, z] for z in (-0.1, 0.0, 0.1) for y in (-1.0, 0.0) for x in (-1.0, 0.0, 1.0)])


@pytest.fixture()
def scan(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    positions = _grid_positions()
    images = rng.integers(100, 4000, size=(len(positions), 12, 16)).astype(np.uint16)
    exposures = np.linspace(1.0, 3.0, len(positions))
    return write_scan(tmp_path / "scan", images, positions, exposures, META)


def _rows(folder: Path) -> list[str]:
    return (folder / "positions.csv").read_text().splitlines()


def _write_rows(folder: Path, rows: list[str]) -> None:
    (folder / "positions.csv").write_text("\n".join(rows) + "\n")


def test_round_trip_keeps_images_positions_exposures_and_meta(scan: Path):
    loaded = read_scan(scan)
    assert isinstance(loaded, PSFScan)
    assert loaded.images.shape == (18, 12, 16) and loaded.images.dtype == np.uint16
    np.testing.assert_allclose(loaded.positions_mm, _grid_positions())
    np.testing.assert_allclose(loaded.exposure_ms, np.linspace(1.0, 3.0, 18))
    assert loaded.meta == META
    xs, ys, zs = loaded.grid_axes_mm()
    np.testing.assert_allclose(xs, [-1, 0, 1])
    np.testing.assert_allclose(ys, [-1, 0])
    np.testing.assert_allclose(zs, [-0.1, 0, 0.1])


def test_normalised_removes_dark_and_divides_by_exposure(scan: Path):
    loaded = read_scan(scan)
    expected = (loaded.images[3].astype(np.float32) - 100.0) / loaded.exposure_ms[3]
    np.testing.assert_allclose(loaded.normalised()[3], expected, rtol=1e-6)
    index = open_scan(scan)
    np.testing.assert_allclose(index.normalised(3), expected, rtol=1e-6)


def test_open_scan_reads_headers_only_and_images_on_demand(scan: Path):
    index = open_scan(scan)
    assert isinstance(index, ScanIndex)
    assert len(index) == 18 and index.shape == (12, 16)
    np.testing.assert_array_equal(index.image(5), read_scan(scan).images[5])
    gi = index.grid_index()
    assert gi.shape == (18, 3)
    np.testing.assert_array_equal(gi[:3], [[0, 0, 0], [1, 0, 0], [2, 0, 0]])


def test_rows_in_any_order_are_fine(scan: Path):
    rows = _rows(scan)
    _write_rows(scan, [rows[0]] + rows[1:][::-1])
    loaded = read_scan(scan)
    assert loaded.positions_mm[0].tolist() == pytest.approx([1.0, 0.0, 0.1])


def test_grid_helpers_on_irregular_but_complete_grids():
    positions = np.array([[x, y, z] for z in (0.0, 0.3) for y in (0.0,) for x in (-2.0, 0.5, 1.0)])
    xs, _, zs = grid_axes_mm(positions)
    assert xs.tolist() == [-2.0, 0.5, 1.0] and zs.tolist() == [0.0, 0.3]
    assert grid_index(positions)[4].tolist() == [1, 0, 1]


# ----------------------------------------------------------------------------- broken scans


def test_missing_file(scan: Path):
    (scan / "psf_00004.tif").unlink()
    with pytest.raises(ScanError, match=r"line 6: psf_00004.tif is missing"):
        read_scan(scan)


def test_extra_file(scan: Path):
    shutil.copy(scan / "psf_00001.tif", scan / "stray.tif")
    with pytest.raises(ScanError, match="not listed in positions.csv: stray.tif"):
        read_scan(scan)


def test_misordered_one_image_on_two_rows(scan: Path):
    rows = _rows(scan)
    rows[5] = rows[5].replace("psf_00004.tif", "psf_00002.tif")
    _write_rows(scan, rows)
    with pytest.raises(ScanError, match=r"psf_00002.tif is also listed on line 4: misordered"):
        read_scan(scan)


def test_misordered_files_swapped_between_rows(scan: Path):
    rows = _rows(scan)
    a, b = rows[2].split(",", 1), rows[3].split(",", 1)
    rows[2], rows[3] = f"{b[0]},{a[1]}", f"{a[0]},{b[1]}"
    _write_rows(scan, rows)
    with pytest.raises(ScanError, match=r"psf_00002.tif was recorded at .* but is listed at .*: misordered files"):
        read_scan(scan)


def test_nan_position(scan: Path):
    rows = _rows(scan)
    rows[3] = rows[3].replace(rows[3].split(",")[2], "nan", 1)
    _write_rows(scan, rows)
    with pytest.raises(ScanError, match=r"line 4: y_mm = 'nan' is not finite"):
        read_scan(scan)


def test_non_numeric_position(scan: Path):
    rows = _rows(scan)
    parts = rows[7].split(",")
    parts[3] = "deep"
    rows[7] = ",".join(parts)
    _write_rows(scan, rows)
    with pytest.raises(ScanError, match=r"line 8: z_mm = 'deep' is not a number"):
        read_scan(scan)


def test_positions_that_do_not_form_a_grid(scan: Path):
    rows = _rows(scan)
    _write_rows(scan, rows[:-1])
    (scan / "psf_00017.tif").unlink()
    with pytest.raises(ScanError, match=r"17 positions do not form a grid .*3×2×3 = 18; 1 grid points have no image"):
        read_scan(scan)


def test_repeated_position(scan: Path):
    rows = _rows(scan)
    first = rows[1].split(",")
    parts = rows[2].split(",")
    rows[2] = ",".join([parts[0], *first[1:4], parts[4]])
    _write_rows(scan, rows)
    with pytest.raises(ScanError, match="occur more than once|recorded at"):
        read_scan(scan)


def test_float_images_with_nan_are_named(scan: Path):
    data = np.full((12, 16), np.nan, np.float32)
    tifffile.imwrite(scan / "psf_00003.tif", data)
    with pytest.raises(
        ScanError, match=r"psf_00003.tif: images must be 16-bit unsigned \(found float32\); it also holds 192 NaN"
    ):
        read_scan(scan)


def test_shape_mismatch(scan: Path):
    tifffile.imwrite(scan / "psf_00006.tif", np.zeros((10, 16), np.uint16))
    with pytest.raises(ScanError, match=r"psf_00006.tif: shape \(10, 16\) differs"):
        read_scan(scan)


def test_corrupt_tiff(scan: Path):
    (scan / "psf_00001.tif").write_bytes(b"not a tiff at all")
    with pytest.raises(ScanError, match="psf_00001.tif: not a readable TIFF"):
        read_scan(scan)


def test_counts_beyond_bit_depth(scan: Path):
    image = np.full((12, 16), 5000, np.uint16)
    tifffile.imwrite(scan / "psf_00000.tif", image)
    index = open_scan(scan)  # headers are fine
    with pytest.raises(ScanError, match="counts up to 5000 exceed bit_depth = 12"):
        index.image(0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m.pop("pixel_um"), "missing pixel_um"),
        (lambda m: m.update(bit_depth=11), "bit_depth = 11"),
        (lambda m: m.update(pixel_um=-1), "pixel_um = -1.0"),
        (lambda m: m.update(dark_level=1e9), "dark_level"),
    ],
)
def test_bad_scan_yaml(scan: Path, change, message):
    meta = yaml.safe_load((scan / "scan.yaml").read_text())
    change(meta)
    (scan / "scan.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(ScanError, match=message):
        read_scan(scan)


def test_bad_columns_and_exposure(scan: Path):
    rows = _rows(scan)
    _write_rows(scan, ["file,x,y,z,exposure_ms"] + rows[1:])
    with pytest.raises(ScanError, match="columns must be file,x_mm,y_mm,z_mm,exposure_ms"):
        read_scan(scan)
    parts = rows[4].split(",")
    parts[4] = "0"
    rows[4] = ",".join(parts)
    _write_rows(scan, rows)
    with pytest.raises(ScanError, match=r"line 5: exposure_ms = 0.0 must be > 0"):
        read_scan(scan)


def test_multipage_tiffs(tmp_path: Path):
    folder = tmp_path / "pages"
    folder.mkdir()
    stack = np.arange(4 * 6 * 5, dtype=np.uint16).reshape(4, 6, 5)
    tifffile.imwrite(folder / "stack.tif", stack, photometric="minisblack")
    (folder / "scan.yaml").write_text(yaml.safe_dump(META.to_dict()))
    rows = ["file,x_mm,y_mm,z_mm,exposure_ms"] + [
        f"stack.tif#{k},{x},0,0,1" for k, x in enumerate((-1.5, -0.5, 0.5, 1.5))
    ]
    _write_rows(folder, rows)
    np.testing.assert_array_equal(read_scan(folder).images, stack)
    _write_rows(folder, rows[:-1] + ["stack.tif#7,1.5,0,0,1"])
    with pytest.raises(ScanError, match=r"stack.tif#7 names no page of stack.tif \(4 pages\)"):
        read_scan(folder)
    _write_rows(folder, rows[:-1] + ["stack.tif,1.5,0,0,1"])
    with pytest.raises(ScanError, match="has 4 pages; name one as stack.tif#K"):
        read_scan(folder)


def test_write_scan_is_atomic_and_embeds_positions(tmp_path: Path):
    with pytest.raises(ScanError):
        write_scan(tmp_path / "bad", np.zeros((2, 4, 4), np.float32), np.zeros((2, 3)), 1.0, META)
    assert not any(tmp_path.iterdir())
    folder = write_scan(tmp_path / "good", np.zeros((1, 4, 4), np.uint16), np.array([[0.25, -0.5, 0.1]]), 2.0, META)
    description = json.loads(tifffile.TiffFile(folder / "psf_00000.tif").pages[0].description)
    assert description["x_mm"] == 0.25 and description["z_mm"] == 0.1 and description["exposure_ms"] == 2.0


def test_pixel_pitch_checked_against_the_sensor(scan: Path):
    assert open_scan(scan, sensor_pixel_um=2.4).meta.pixel_um == 2.4
    with pytest.raises(ScanError, match=r"scan.yaml: pixel_um = 2.4 contradicts binning = 1 × the sensor's 0.6 µm"):
        open_scan(scan, sensor_pixel_um=0.6)
