"""CM²Net: config validation and hash, refocusing shifts from the model geometry (and their
sign), the network's shapes at any size, the losses, on-the-fly patches (aligned with the synth
package's volume patches, reproducible), weights files (hash, config mismatch) and full-field
inference with its input and geometry checks. Tiny sizes: each test takes a few seconds."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch
from tiny_net import SYNTH, tiny

from cm2optics.lsv.toy import gaussian_lsi_operator as gaussian_cm2
from cm2optics.recon.net.config import ConfigError, NetConfig, load_config
from cm2optics.recon.net.data import PatchSource, epoch_items
from cm2optics.recon.net.infer import histogram_match, reconstruct_with_net
from cm2optics.recon.net.loss import cm2net_loss, volume_loss
from cm2optics.recon.net.model import CM2Net, build_net, fused_for_inference
from cm2optics.recon.net.refocus import ShiftAndAdd, refocus_planes
from cm2optics.recon.net.train import make_net, start_from_weights
from cm2optics.recon.net.weights import (
    SUMS_FILE,
    WEIGHTS_FILE,
    GeometryMismatchError,
    NetInputError,
    WeightsError,
    load_weights,
    save_weights,
)
from cm2optics.synth.config import SynthConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ----------------------------------------------------------------------------- config
def test_config_validates_fields_and_round_trips_through_yaml(tmp_path):
    with pytest.raises(ConfigError, match="channels"):
        tiny(channels=0)
    with pytest.raises(ConfigError, match="n_planes"):
        tiny(n_planes=80)
    with pytest.raises(ConfigError, match="volume_loss"):
        tiny(volume_loss="dice")
    with pytest.raises(ConfigError, match="unknown CM²Net parameter"):
        NetConfig.from_dict({"width": 3})
    config = tiny(volume_loss="focal", curriculum_epochs=3)
    path = config.save(tmp_path / "c.yaml")
    again = load_config(path)
    assert again == config and again.hash() == config.hash()
    # runtime fields do not change the hash, the rest does
    assert config.with_changes(epochs=99, out_dir="elsewhere", threads=2).hash() == config.hash()
    assert config.with_changes(channels=16).hash() != config.hash()
    (tmp_path / "bad.yaml").write_text("channels: many\n")
    with pytest.raises(ConfigError, match="bad.yaml.*channels"):
        load_config(tmp_path / "bad.yaml")


# ----------------------------------------------------------------------------- refocusing
def test_refocusing_planes_from_the_geometry_match_the_paper_at_full_size(v2):
    """The analytic CM² V2's geometry at full resolution: the paper's fixed 36 planes have
    disparities −18…+17 px and the neighbouring views shift by the disparity; auto planes span
    the 800-µm depth at one pixel of disparity each; depths increase with the plane index."""
    from cm2optics.lsv.toy import AnalyticCM2, analytic_geometry

    model = AnalyticCM2.from_design(v2)
    source = types.SimpleNamespace(geometry=analytic_geometry(model, np.linspace(-0.8, 0.8, 9)))
    planes = refocus_planes(source, (-0.4, 0.4), 36)
    assert planes.n_planes == 36 and planes.disparity_px.min() == -18 and planes.disparity_px.max() == 17
    assert np.all(np.diff(planes.z_mm) > 0)
    # centre lenslet (index 4) never moves; a side neighbour moves by ≈ the disparity
    assert np.all(planes.shifts_px[:, 4] == 0)
    side = np.abs(planes.shifts_px[:, 5]).sum(axis=1)
    np.testing.assert_allclose(side, np.abs(planes.disparity_px), atol=1)
    auto = refocus_planes(source, (-0.4, 0.4), 0)
    assert 15 <= auto.n_planes <= 40  # one plane per pixel of disparity over 0.8 mm
    assert auto.z_mm.min() >= -0.4 - 1e-9 and auto.z_mm.max() <= 0.4 + 1e-9


def test_refocusing_planes_of_a_scan_fitted_geometry_that_turns_far_outside_the_scan(v2):
    """Regression: a geometry fitted to a ±0.4-mm scan is quadratic in z and may turn back far
    outside the scan (here at z = 1.5 mm); an 800-µm volume still gets its planes (the search
    for the paper's fixed 36 widens only as far as they need), and a turn inside the volume is
    still refused."""
    from cm2optics.lsv.toy import AnalyticCM2, analytic_geometry

    g = analytic_geometry(AnalyticCM2.from_design(v2), np.linspace(-0.4, 0.4, 5))
    straight = refocus_planes(types.SimpleNamespace(geometry=g), (-0.4, 0.4), 0)

    def bent(turn_mm):
        o = np.array(g.o_poly, float, copy=True)
        o[2] = -o[1] / (2 * turn_mm)  # d(z) ∝ z − z²/(2·turn): extremum at z = turn
        return types.SimpleNamespace(geometry=type(g)(g.r0_poly, g.A_poly, o, g.rows, g.cols))

    auto = refocus_planes(bent(1.5), (-0.4, 0.4), 0)
    assert 15 <= auto.n_planes <= 40 and abs(auto.n_planes - straight.n_planes) <= 2
    assert np.all(np.diff(auto.z_mm) > 0) and auto.z_mm.min() >= -0.4 - 1e-9 and auto.z_mm.max() <= 0.4 + 1e-9
    fixed = refocus_planes(bent(1.5), (-0.4, 0.4), 36)
    assert fixed.n_planes == 36 and fixed.disparity_px.min() == -18 and fixed.disparity_px.max() == 17
    with pytest.raises(ValueError, match="not monotonic in depth over the volume"):
        refocus_planes(bent(0.2), (-0.4, 0.4), 0)


def test_shift_and_add_brings_a_point_into_focus_at_its_depth():
    grid = SYNTH.grid
    op = gaussian_cm2(grid, (160, 160), defocus_px_per_um=0.006)
    planes = refocus_planes(op, (grid.axis_mm(0)[0], grid.axis_mm(0)[-1]), 0)
    from cm2optics.synth.views import crop_views

    for k in (0, planes.n_planes // 2, planes.n_planes - 1):
        iz = int(np.argmin(np.abs(grid.axis_mm(0) - planes.z_mm[k])))
        volume = np.zeros(grid.shape, np.float32)
        volume[iz, 20, 27] = 1.0
        views = crop_views(np.asarray(op.forward(volume, per_lenslet=True)), op.chief_rays_px(), 64)
        stack = ShiftAndAdd(planes.shifts_px)(torch.from_numpy(views)[None])[0].numpy()
        best = int(np.argmax(stack.reshape(len(stack), -1).max(axis=1)))
        assert abs(planes.z_mm[best] - grid.axis_mm(0)[iz]) <= 0.5 * np.diff(planes.z_mm).mean() + 1e-9


def test_shift_and_add_fills_zeros_rather_than_wrapping():
    shifts = np.zeros((1, 2, 2), np.int64)
    shifts[0, 1] = (0, 3)
    views = torch.zeros(1, 2, 4, 6)
    views[0, 1, :, -1] = 1.0  # the last column of view 1
    out = ShiftAndAdd(shifts)(views)[0, 0]
    assert float(out[:, -1].sum()) == 0.0 and float(out[:, 2].sum()) == pytest.approx(4 * 0.5)


# ----------------------------------------------------------------------------- network
def test_the_network_is_fully_convolutional_and_its_first_enhancement_layer_resamples_planes():
    config = tiny()
    net, border = make_net(config)
    assert isinstance(net, CM2Net) and border == net.planes.max_shift_px
    net.eval()
    with torch.no_grad():
        demix, volume = net(torch.rand(1, 9, 40, 56))
    assert demix.shape == (1, 9, 40, 56) and volume.shape == (1, config.n_planes, 40, 56)
    W = net.resample.weight[:, :, 0, 0].detach().numpy()
    assert W.shape == (config.n_planes, net.planes.n_planes)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-6)  # linear interpolation in z
    assert float(torch.sigmoid(volume).mean()) < 0.1  # sparse prior at the start
    with pytest.raises(ValueError, match="views must be"):
        net(torch.rand(1, 4, 8, 8))


def test_losses_are_finite_and_the_border_is_left_out():
    config = tiny()
    logits = torch.randn(2, 9, 16, 16)
    target = (torch.rand(2, 9, 16, 16) > 0.95).float()
    for kind in ("bce", "weighted-bce", "focal"):
        assert torch.isfinite(volume_loss(logits, target, kind))
    assert volume_loss(logits, target, "focal") < volume_loss(logits, target, "bce")
    vol_logits = torch.full((1, 3, 16, 16), -5.0)
    vol_logits[..., 0, :] = 5.0  # wrong only on the border
    total, parts = cm2net_loss(
        torch.zeros(1, 9, 16, 16), vol_logits, torch.zeros(1, 9, 16, 16), torch.zeros(1, 3, 16, 16), config, 2
    )
    assert float(parts["volume"]) < 0.01 and torch.isfinite(total)


# ----------------------------------------------------------------------------- data
def test_interleaved_volumes_give_each_of_g_workers_one_volume_of_the_same_items():
    plain = tiny(train_volumes=5, batch_size=2, synth=SYNTH.with_changes(patches_per_volume=7))
    mixed = plain.with_changes(interleave_volumes=3)
    assert plain.hash() != mixed.hash()  # 1 (the default) stays out of the hash: the shipped weights load
    a, b = epoch_items(plain, 1), epoch_items(mixed, 1)
    assert sorted(a, key=lambda i: (i.volume, i.patch)) == sorted(b, key=lambda i: (i.volume, i.patch))
    volume_order = list(dict.fromkeys(i.volume for i in a))  # the plain order: a volume's patches in a row
    for v in volume_order:
        assert [i.patch for i in a if i.volume == v] == [i.patch for i in b if i.volume == v]
    # group 1 = the first 3 volumes: 3 full batches each, batch j from its volume j mod 3; then the
    # leftover patch of each; then group 2 (2 volumes) likewise
    batches = [b[k : k + 2] for k in range(0, 18, 2)]
    for j, batch in enumerate(batches):
        assert {i.volume for i in batch} == {volume_order[j % 3]}
    assert [i.volume for i in b[18:21]] == volume_order[:3]
    assert {i.volume for i in b[21:23]} == {volume_order[3]} and {i.volume for i in b[23:25]} == {volume_order[4]}
    with pytest.raises(ConfigError, match="interleave_volumes"):
        tiny(interleave_volumes=0)


def test_patch_targets_are_the_synth_volume_patches_and_reproducible():
    from cm2optics.synth.raster import rasterize_balls
    from cm2optics.synth.views import volume_patch

    config = tiny()
    source = PatchSource(config)
    item = epoch_items(config, 0)[0]
    made = source.volume(item.seed, item.volume, item.density)
    full = np.clip(rasterize_balls(made["emitters"], config.synth.grid, kind="occupancy"), 0, 1)
    for k, origin in enumerate(made["origins"]):
        expected, _ = volume_patch(full, origin, config.synth.view_px, config.synth.patch_px, source.scale)
        np.testing.assert_allclose(made["volume"][k], expected, atol=1e-5)
    other = PatchSource(config).volume(item.seed, item.volume, item.density)
    for key in ("views", "demixed", "volume"):
        np.testing.assert_array_equal(made[key], other[key])
    # the true emitters in a patch's frame sit where the target's voxels are
    k = int(np.argmax(made["volume"].reshape(4, -1).sum(1)))
    truth = source.truth(type(item)(item.seed, item.volume, k, item.density), 0)
    if len(truth):
        g = config.synth.grid
        iy = np.round(truth.y_um / g.voxel_um[1] + (config.synth.patch_px - 1) / 2).astype(int)
        ix = np.round(truth.x_um / g.voxel_um[2] + (config.synth.patch_px - 1) / 2).astype(int)
        iz = np.round(truth.z_um / g.voxel_um[0] + (g.shape[0] - 1) / 2).astype(int)
        ok = (iz >= 0) & (iz < g.shape[0])
        hit = made["volume"][k][iz[ok], iy[ok], ix[ok]] > 0
        # balls thinner than the 100-µm z voxels may miss every fine sub-voxel: most must hit
        assert hit.mean() >= 0.5


def test_curriculum_grows_the_density():
    from cm2optics.recon.net.data import density_at

    config = tiny(curriculum_epochs=4, curriculum_start_density=(1.0, 2.0))
    assert density_at(config, 0) == (1.0, 2.0)
    assert density_at(config, 4) == tuple(config.synth.density_per_mm2) == density_at(config, 9)
    lows = [density_at(config, e)[1] for e in range(5)]
    assert all(b > a for a, b in zip(lows, lows[1:], strict=False))


# ----------------------------------------------------------------------------- weights, inference
@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    config = tiny()
    net, _ = make_net(config)
    return save_weights(
        net, config, tmp_path_factory.mktemp("w") / "weights", metrics={"f1": 0.5}, histogram=np.linspace(0, 1, 256)
    )


def test_weights_round_trip_and_refuse_a_failed_hash_or_another_config(weights, tmp_path):
    import shutil

    loaded = load_weights(weights)
    assert "CM²Net model card" in (weights / "MODEL_CARD.md").read_text()
    x = torch.rand(1, 9, 32, 32)
    again = load_weights(weights)
    with torch.no_grad():
        np.testing.assert_array_equal(loaded.net(x)[1].numpy(), again.net(x)[1].numpy())
    bad = shutil.copytree(weights, tmp_path / "corrupt")
    data = bytearray((bad / WEIGHTS_FILE).read_bytes())
    data[-5] ^= 0xFF
    (bad / WEIGHTS_FILE).write_bytes(bytes(data))
    with pytest.raises(WeightsError, match=r"model\.safetensors.*SHA-256"):
        load_weights(bad)
    # another config (sums recomputed so that only the mismatch remains)
    other = shutil.copytree(weights, tmp_path / "other")
    text = (other / "config.yaml").read_text().replace("channels: 8", "channels: 16")
    (other / "config.yaml").write_text(text)
    import hashlib

    sums = "".join(
        f"{hashlib.sha256((other / n).read_bytes()).hexdigest()}  {n}\n" for n in (WEIGHTS_FILE, "config.yaml")
    )
    (other / SUMS_FILE).write_text(sums)
    with pytest.raises(WeightsError, match="config"):
        load_weights(other)
    (other / SUMS_FILE).unlink()
    with pytest.raises(WeightsError, match=SUMS_FILE):
        load_weights(other)


def test_a_forward_model_shipped_in_the_weights_folder_is_found_there_and_checked(tmp_path, monkeypatch):
    """reconstruction/cm2net-cpu-traced names its 3D-LSV model relative to the folder: found
    from any directory, and refused when it is edited or missing."""
    import shutil
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[2] / "reconstruction" / "cm2net-cpu-traced"
    monkeypatch.chdir(tmp_path)
    loaded = load_weights(shipped)
    assert Path(loaded.config.forward_model) == (shipped / "forward_model.lsv.h5").resolve()
    copy = shutil.copytree(shipped, tmp_path / "copy")
    model = copy / "forward_model.lsv.h5"
    data = bytearray(model.read_bytes())
    data[-3] ^= 0xFF
    model.write_bytes(bytes(data))
    with pytest.raises(WeightsError, match=r"forward_model\.lsv\.h5.*SHA-256"):
        load_weights(copy)
    model.unlink()
    with pytest.raises(WeightsError, match=r"forward_model\.lsv\.h5: missing"):
        load_weights(copy)


def test_full_field_inference_checks_its_inputs_and_returns_a_volume(weights):
    from cm2optics.synth.generate import synthesize_sample
    from cm2optics.synth.imaging import Imaging

    config = load_weights(weights).config
    grid = config.synth.grid
    op = gaussian_cm2(grid, (160, 160), defocus_px_per_um=0.006)
    sample = synthesize_sample(config.synth.with_changes(patches_per_volume=0), Imaging(op, grid), 0, 3)
    result = reconstruct_with_net(sample.measurement, weights, op, preprocess="histogram", threshold=0.2)
    assert result.volume.shape == (config.n_planes, 64, 64) and result.grid.voxel_um == grid.voxel_um
    assert result.volume.dtype == np.float32 and 0 <= result.volume.min() and result.volume.max() <= 1
    assert result.border_px == load_weights(weights).planes.max_shift_px and result.demixed.shape == (9, 64, 64)
    with pytest.raises(NetInputError, match="shape"):
        reconstruct_with_net(sample.measurement[:100], weights, op)
    with pytest.raises(NetInputError, match="dtype"):
        reconstruct_with_net(sample.measurement.astype(complex), weights, op)
    with pytest.raises(NetInputError, match="NaN"):
        reconstruct_with_net(np.full((160, 160), np.nan), weights, op)
    other = gaussian_cm2(grid, (160, 160), defocus_px_per_um=0.006, shear_per_um=6e-4)
    with pytest.raises(GeometryMismatchError, match="refocusing"):
        reconstruct_with_net(sample.measurement, weights, other)


def test_folding_the_batch_norms_into_the_convolutions_keeps_the_outputs(weights):
    net = load_weights(weights).net
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):  # statistics and scales far from the identity
                m.running_mean.uniform_(-0.5, 0.5), m.running_var.uniform_(0.2, 3.0)
                m.weight.uniform_(0.5, 2.0), m.bias.uniform_(-0.3, 0.3)
    net.eval()
    fused = fused_for_inference(net)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())  # the original is untouched
    x = torch.rand(1, 9, 40, 48)
    with torch.no_grad():
        (d0, v0), (d1, v1) = net(x), fused(x)
    assert float((v0 - v1).abs().max()) < 1e-4 * max(1.0, float(v0.abs().max()))
    assert float((d0 - d1).abs().max()) < 1e-4 * max(1.0, float(d0.abs().max()))


def test_fine_tuning_starts_from_the_weights_with_the_refocusing_of_its_own_model(weights):
    """start_from_weights: the learned tensors come over, the refocusing stays the new model's,
    and the resampling's interpolation moves onto the new planes (here the weights are untrained,
    so the resampling must become exactly the new planes' interpolation)."""
    loaded = load_weights(weights)
    config = loaded.config
    z = config.synth.grid.axis_mm(0)
    other = gaussian_cm2(config.synth.grid, (160, 160), defocus_px_per_um=0.006, shear_per_um=6e-4)
    planes = refocus_planes(other, (float(z[0]), float(z[-1])), loaded.planes.n_planes)
    assert not np.allclose(planes.z_mm, loaded.planes.z_mm)
    net = build_net(config, planes, z, seed=123)
    start_from_weights(net, weights)
    np.testing.assert_array_equal(net.demix[0].weight.detach().numpy(), loaded.net.demix[0].weight.detach().numpy())
    np.testing.assert_array_equal(net.refocus.shifts.numpy(), planes.shifts_px)
    np.testing.assert_allclose(net.refocus_z_mm.numpy(), planes.z_mm)
    np.testing.assert_allclose(net.resample.weight[:, :, 0, 0].detach().numpy(), planes.resampling(z), atol=1e-6)
    narrow = build_net(config.with_changes(channels=4), planes, z)
    with pytest.raises(ValueError, match="architecture"):
        start_from_weights(narrow, weights)


def test_cm2_reconstruct_method_net_writes_the_volume_record_and_emitters(weights, tmp_path):
    """`cm2 reconstruct MEAS --method net --weights DIR`: the model defaults to the weights' own
    (whole sensor), the volume, its JSON record and the emitter CSV are written; misuse is one line."""
    import json

    from typer.testing import CliRunner

    from cm2optics.cli import app
    from cm2optics.formats.emitters import read_emitters
    from cm2optics.formats.volume import read_volume
    from cm2optics.recon.net.data import inference_model
    from cm2optics.synth.generate import synthesize_sample
    from cm2optics.synth.imaging import Imaging

    config = load_weights(weights).config
    model = inference_model(config)
    assert tuple(model.sensor_shape) == (config.toy_sensor_px,) * 2
    grid = config.synth.grid
    sample = synthesize_sample(config.synth.with_changes(patches_per_volume=0), Imaging(model, grid), 0, 3)
    np.save(tmp_path / "meas.npy", sample.measurement)
    (tmp_path / "empty").mkdir()
    runner = CliRunner()
    args = ["reconstruct", str(tmp_path / "meas.npy"), "--method", "net", "--weights", str(weights)]
    result = runner.invoke(
        app, [*args, "--preprocess", "none", "--threshold", "0.3", "--emitters-out", str(tmp_path / "e.csv"), "--json"]
    )
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    volume_path = tmp_path / "meas.volume.tif"
    assert record["volume"] == str(volume_path) and record["threshold"] == 0.3 and record["method"] == "net"
    assert record["lateral_correction"] is None  # these weights were never calibrated
    volume, volume_grid = read_volume(volume_path)
    assert volume.shape == (config.n_planes, config.synth.view_px, config.synth.view_px)
    np.testing.assert_allclose(volume_grid.voxel_um, grid.voxel_um, rtol=1e-4)
    assert json.loads((tmp_path / "meas.volume.json").read_text())["n_emitters"] == len(
        read_emitters(tmp_path / "e.csv")
    )
    # --field-mm: views that hold a wider disc than the training views' (the whole field of a frame)
    from cm2optics.recon.net.infer import field_view_px

    assert field_view_px(7.0, 4.15, 5) == 1732  # 1,687 voxels · 1.02 + 10 px of border, even
    wide = 2.0 * config.synth.fov_mm[1]
    side = field_view_px(wide, grid.voxel_um[1], load_weights(weights).planes.max_shift_px)
    result = runner.invoke(
        app, [*args, "--preprocess", "none", "--field-mm", str(wide), "--out", str(tmp_path / "wide.npy"), "--json"]
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["view_px"] == side > config.synth.view_px
    assert np.load(tmp_path / "wide.npy").shape == (config.n_planes, side, side)
    for extra, message in (
        ([], "exists; pass --overwrite"),  # the volume is there now
        (["--out", str(tmp_path / "v.tif"), "--weights", str((tmp_path / "empty").resolve())], "empty"),
        (["--out", str(tmp_path / "v.tif"), "--preprocess", "gamma"], "--preprocess"),
        (["--out", str(tmp_path / "v.tif"), "--threshold", "1.5"], "--threshold"),
    ):
        failed = runner.invoke(app, [*args, *extra])
        assert failed.exit_code == 2 and message in failed.output, failed.output
    failed = runner.invoke(
        app, ["reconstruct", str(tmp_path / "meas.npy"), "--method", "net", "--out", str(tmp_path / "w.tif")]
    )
    assert failed.exit_code == 2 and "--weights" in failed.output
    failed = runner.invoke(app, ["reconstruct", str(tmp_path / "meas.npy"), "--out", str(tmp_path / "w.tif")])
    assert failed.exit_code == 2 and "--model" in failed.output
    failed = runner.invoke(
        app, ["reconstruct", str(tmp_path / "meas.npy"), "--field-mm", "2", "--out", str(tmp_path / "w.tif")]
    )
    assert failed.exit_code == 2 and "--field-mm go with --method net" in failed.output


def test_histogram_matching_maps_quantiles():
    rng = np.random.default_rng(0)
    image = rng.exponential(3.0, (64, 64))
    ref = np.quantile(rng.normal(0.1, 0.02, 10_000), np.linspace(0, 1, 256))
    out = histogram_match(image, ref)
    assert abs(np.median(out) - np.median(ref)) < 0.005
    assert np.all(np.diff(out.ravel()[np.argsort(image.ravel())]) >= -1e-7)  # order kept


def test_the_sensor_window_gives_the_full_sensors_views(v2):
    """The 3D-LSV model cut to the window the views need renders the same views (analytic CM²
    V2, binned 8×), on a smaller sensor."""
    from cm2optics.lsv.toy import AnalyticCM2, analytic_lsv_model
    from cm2optics.recon.net.data import sensor_window
    from cm2optics.synth.generate import synthesize_sample
    from cm2optics.synth.imaging import Imaging

    analytic = AnalyticCM2.from_design(v2, binning=8, sigma0_um=19.2)
    xs = np.linspace(-1.2, 1.2, 3)
    model = analytic_lsv_model(analytic, xs, xs, np.linspace(-0.2, 0.2, 3), rank=4)
    window = sensor_window(model, 48)
    assert window.sensor_shape[0] * window.sensor_shape[1] < 0.8 * model.sensor_shape[0] * model.sensor_shape[1]
    voxel = model.default_grid.voxel_um[1]
    synth = SynthConfig.scaled(
        8, voxel_um=(50.0, voxel, voxel), view_px=48, patch_px=16, patches_per_volume=0, noise="none", depth_um=300.0
    )
    a = synthesize_sample(synth, Imaging(model, synth.grid), 0, 5)
    b = synthesize_sample(synth, Imaging(window, synth.grid), 0, 5)
    assert a.views.max() > 0
    np.testing.assert_allclose(
        b.views * b.image_scale, a.views * a.image_scale, atol=1e-4 * a.image_scale * a.views.max()
    )
    np.testing.assert_allclose(
        b.demixed * b.image_scale, a.demixed * a.image_scale, atol=1e-4 * a.image_scale * a.views.max()
    )


def test_the_learning_rate_drops_by_the_factor_after_two_stalled_epochs():
    from cm2optics.recon.net.train import make_optimiser, make_scheduler

    config = tiny()
    net, _ = make_net(config)
    optimiser = make_optimiser(net, config)
    scheduler = make_scheduler(optimiser, config)
    lrs = []
    for loss in (1.0, 1.0, 1.0, 1.0, 1.0):
        scheduler.step(loss)
        lrs.append(optimiser.param_groups[0]["lr"])
    assert lrs[:2] == [1e-4, 1e-4] and lrs[2] == pytest.approx(0.9e-4)  # best, stalled, stalled → ×0.9


def test_the_training_entry_point_reports_a_bad_config_without_a_traceback(tmp_path, capsys):
    from cm2optics.recon.net.train import main

    assert main([str(tmp_path / "missing.yaml")]) == 2
    assert "no such config file" in capsys.readouterr().out
