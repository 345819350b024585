"""The formats layer: one emitter reader (lenient layout, strict values), measurement + sidecar,
the LSV model file (HDF5 and NPZ), model dispatch, and the FFT length rule."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from cm2optics.formats.emitters import Emitters, read_emitters
from cm2optics.formats.measurement import MeasurementError, read_measurement, read_sidecar, write_measurement
from cm2optics.formats.models import ModelFormatError, load_forward_model, model_format, model_grid
from cm2optics.formats.operator import VolumeOperator
from cm2optics.formats.volume import VolumeError, VolumeGrid, read_volume, write_volume
from cm2optics.lsv.operators import fast_length

SIDECAR = {
    "pixel_um": 19.2,
    "bit_depth": 12,
    "dark_level": 0.0,
    "counts_per_unit": 100.0,
    "noise": None,
    "generator": "test",
}


def test_emitters_any_column_order_comments_and_errors_with_lines(tmp_path):
    path = tmp_path / "e.csv"
    path.write_text(
        "# made by hand\n\nintensity,z_um,y_um,x_um,diameter_um,note\n1,3,2,1,10,a\n# a comment between rows\n0.5,-3,0,4,0,b\n"
    )
    emitters = read_emitters(path)
    np.testing.assert_allclose(emitters.positions_um, [[1, 2, 3], [4, 0, -3]])
    np.testing.assert_allclose(emitters.intensity, [1, 0.5])
    assert len(Emitters.from_positions_um(emitters.positions_um, emitters.diameter_um, emitters.intensity)) == 2
    path.write_text("# header below\nx_um,y_um,z_um,diameter_um,intensity\n1,2,3,4,5\n1,2,x,4,5\n")
    with pytest.raises(VolumeError, match=r"e.csv line 4: z_um = 'x' is not a number"):
        read_emitters(path)
    path.write_text("x_um,y_um,diameter_um\n1,2,3\n")
    with pytest.raises(VolumeError, match=r"e.csv line 1: columns must be .* \(missing z_um, intensity"):
        read_emitters(path)


def test_measurement_and_sidecar_round_trip_and_schema(tmp_path):
    counts = np.arange(12, dtype=np.uint16).reshape(3, 4)
    tif, side = write_measurement(tmp_path / "m.tif", counts, SIDECAR | {"design": "cm2-v2"})
    assert list(yaml.safe_load(side.read_text()))[:6] == list(SIDECAR)
    assert read_sidecar(tif)["design"] == "cm2-v2"
    np.testing.assert_array_equal(read_measurement(tif, dark_level=1.0), counts.astype(np.float32) - 1)
    with pytest.raises(MeasurementError, match="sidecar misses counts_per_unit"):
        write_measurement(tmp_path / "n.tif", counts, {k: v for k, v in SIDECAR.items() if k != "counts_per_unit"})
    with pytest.raises(MeasurementError, match="exceed bit_depth = 12"):
        write_measurement(tmp_path / "n.tif", np.full((2, 2), 5000, np.uint16), SIDECAR)
    side.write_text(yaml.safe_dump(SIDECAR | {"pixel_um": -1}))
    with pytest.raises(MeasurementError, match=r"m.yaml: pixel_um = -1"):
        read_sidecar(tif)
    assert read_sidecar(tmp_path / "none.tif") is None


def test_one_plane_volume_and_a_2d_reconstruction(tmp_path):
    path = write_volume(tmp_path / "v.tif", np.ones((1, 4, 5), np.float32), (10.0, 4.0, 4.0))
    assert read_volume(path, require_3d=True)[0].shape == (1, 4, 5)
    np.save(tmp_path / "img.npy", np.ones((4, 5), np.float32))
    assert read_volume(tmp_path / "img.npy", (1.0, 1.0, 1.0))[0].shape == (1, 4, 5)
    with pytest.raises(VolumeError, match="not a 3-D volume"):
        read_volume(tmp_path / "img.npy", (1.0, 1.0, 1.0), require_3d=True)


def test_model_dispatch_and_the_lsv_file_in_hdf5_and_npz(tmp_path):
    from cm2optics.lsv.lsi import DepthwiseConvOperator
    from cm2optics.lsv.toy import gaussian_lsi_operator

    grid = VolumeGrid((3, 12, 12), (20.0, 4.0, 4.0))
    stack = gaussian_lsi_operator(grid, (40, 40)).save(tmp_path / "toy.h5")
    assert model_format(stack) == "cm2optics-psf-stack" and model_grid(stack) == grid
    operator = load_forward_model(stack)
    assert isinstance(operator, DepthwiseConvOperator) and isinstance(operator, VolumeOperator)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(ModelFormatError, match="junk.h5: not an HDF5 model file"):
        load_forward_model(tmp_path / "junk.h5")
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "something-else"
    with pytest.raises(ModelFormatError, match="unknown model format 'something-else'"):
        load_forward_model(tmp_path / "other.h5")


def test_lsv_model_file_hdf5_and_npz_agree(tmp_path, v2):
    from cm2optics.lsv.model import LSVModel, ModelError, load_model
    from cm2optics.lsv.toy import AnalyticCM2, analytic_lsv_model

    model = analytic_lsv_model(
        AnalyticCM2.from_design(v2, binning=8),
        np.linspace(-1, 1, 3),
        np.linspace(-1, 1, 3),
        np.array([0.0, 0.2]),
        rank=3,
    )
    for name in ("m.h5", "m.npz"):
        path = model.save(tmp_path / name)
        back = load_forward_model(path)
        assert isinstance(back, LSVModel) and model_grid(path) == model.default_grid
        np.testing.assert_array_equal(back.basis, model.basis)
        np.testing.assert_array_equal(back.geometry.A_poly, model.geometry.A_poly)
        assert back.provenance == model.provenance and back.sensor_shape == model.sensor_shape
    (tmp_path / "bad.npz").write_bytes(b"PK garbage")
    with pytest.raises(ModelError, match="bad.npz: not a readable LSV model"):
        load_model(tmp_path / "bad.npz")


@pytest.mark.parametrize("n", [1, 2, 5, 7, 100, 513, 700, 1000, 1537, 4097])
def test_fast_length_is_the_smallest_documented_size(n):
    """≥ n, of the form 2^a, 3·2^a or 9·2^a, and the smallest such."""
    length = fast_length(n)
    assert length >= n
    m = length
    while m % 2 == 0:
        m //= 2
    assert m in (1, 3, 9)
    assert not any(fast_length(k) == k for k in range(n, length)) or length == n
