"""Issue 15's test set (a) on a tiny case: volumes of a seed the run never used, made through the
weights' own 3D-LSV model at the paper's densities and diameters, scored for the network and for
FISTA through the same model."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from tiny_net import tiny

from cm2optics.recon.net.data import VALIDATION_SEED_OFFSET
from cm2optics.recon.net.testset import TEST_SEED, net_test_set
from cm2optics.recon.net.train import make_net
from cm2optics.recon.net.weights import save_weights
from cm2optics.synth.config import SynthConfig


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def lsv_weights(lsv_model_path, lsv_model, tmp_path_factory):
    """Untrained tiny weights whose forward model is the shared 8×-binned LSV model (one view pixel
    per 32.9-µm voxel, 7 planes 50 µm apart over 300 µm, 64-px views)."""
    voxel = lsv_model.default_grid.voxel_um[1]
    synth = SynthConfig.scaled(
        4,
        voxel_um=(50.0, voxel, voxel),
        depth_um=300.0,
        view_px=64,
        patch_px=32,
        patches_per_volume=2,
        density_per_mm2=(20.0, 40.0),
    )
    config = tiny(forward_model=str(lsv_model_path), synth=synth, n_planes=synth.grid.shape[0], seed=3)
    net, _ = make_net(config)
    return save_weights(net, config, tmp_path_factory.mktemp("lsv-weights") / "weights")


def test_the_test_set_uses_a_seed_no_training_volume_used_and_scores_net_and_fista(lsv_weights, tmp_path):
    for used in (3, 3 + VALIDATION_SEED_OFFSET):
        with pytest.raises(ValueError, match=f"seed {used} is the"):
            net_test_set(lsv_weights, tmp_path / "refused", seed=used, log=None)
    assert not (tmp_path / "refused").exists()
    summary = net_test_set(lsv_weights, tmp_path / "a", n_volumes=2, fista_iterations=4, workers=0, log=None)
    assert summary["seed"] == TEST_SEED != 3 and summary["n_volumes"] == 2
    assert summary["config"]["density_per_mm2"] == [10.0, 100.0] and summary["config"]["diameter_um"] == [8.0, 20.0]
    manifest = json.loads((tmp_path / "a" / "testset" / "manifest.json").read_text())
    assert manifest["seed"] == TEST_SEED
    assert all(10.0 <= s["density_per_mm2"] <= 100.0 for s in manifest["samples"])
    assert set(summary["runs"]) == {"cm2net", "lsv-fista"}
    assert summary["runs"]["cm2net"]["variant"] == "cm2net"
    for name, run in summary["runs"].items():
        for key in ("recall", "precision", "f1"):
            assert 0.0 <= run[key] <= 1.0, (name, key)
        tp, fp, fn = run["n_tp"], run["n_fp"], run["n_fn"]
        assert tp + fn == summary["n_emitters"], name  # every true emitter is matched or missed
        if tp:
            np.testing.assert_allclose(run["f1"], 2 * tp / (2 * tp + fp + fn), rtol=1e-6)
    assert (tmp_path / "a" / "comparison.md").read_text().count("cm2net") >= 1
