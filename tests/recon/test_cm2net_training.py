"""CM²Net training: a tiny run writes its files; a run stopped after some steps and resumed ends
with the weights of an uninterrupted run; two DDP processes (torchrun, gloo) follow the loss curve
of one process with the same global batch; a resume with another config is refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_net import tiny as tiny_config

from cm2optics.recon.net.checkpoint import CheckpointError
from cm2optics.recon.net.config import NetConfig
from cm2optics.recon.net.train import train
from cm2optics.recon.net.weights import load_weights

REPO = Path(__file__).resolve().parents[2]


def tiny(out: Path, **changes) -> NetConfig:
    """The shared tiny configuration, two epochs, writing into ``out``."""
    return tiny_config(**{"epochs": 2, "out_dir": str(out), **changes})


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _state(folder: Path) -> dict[str, torch.Tensor]:
    return load_weights(folder / "weights").net.state_dict()


def test_a_stopped_and_resumed_run_ends_with_the_weights_of_an_uninterrupted_one(tmp_path):
    whole = train(tiny(tmp_path / "whole"))
    assert whole["global_step"] == 8 and not whole["stopped"]
    for name in (
        "checkpoint.pt",
        "history.json",
        "loss_curve.png",
        "weights/model.safetensors",
        "weights/MODEL_CARD.md",
    ):
        assert (tmp_path / "whole" / name).is_file()
    history = json.loads((tmp_path / "whole" / "history.json").read_text())
    assert len(history["steps"]) == 8 and len(history["epochs"]) == 2 and "recall" in history["epochs"][0]

    config = tiny(tmp_path / "parts", volume_loss="bce")
    first = train(config, max_steps=3)  # stopped mid-epoch (4 steps per epoch)
    assert first["stopped"] and first["global_step"] == 3
    assert not (tmp_path / "parts" / "weights").exists()
    second = train(config, max_steps=5, resume=True)  # into the second epoch
    assert second["stopped"] and second["global_step"] == 5
    third = train(config, resume=True)
    assert third["global_step"] == 8 and not third["stopped"]
    a, b = _state(tmp_path / "whole"), _state(tmp_path / "parts")
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)
    resumed = json.loads((tmp_path / "parts" / "history.json").read_text())
    np.testing.assert_array_equal([s["loss"] for s in resumed["steps"]], [s["loss"] for s in history["steps"]])

    with pytest.raises(CheckpointError, match="config"):
        train(config.with_changes(channels=4), resume=True)


def test_the_loss_curve_of_two_ddp_processes_equals_one_process(tmp_path):
    one = tiny(tmp_path / "one", epochs=1, val_volumes=0)
    two = one.with_changes(out_dir=str(tmp_path / "two"))
    train(one)
    config_path = two.save(tmp_path / "two.yaml")
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "cm2optics.recon.net.train",
        str(config_path),
        "--device",
        "cpu",
    ]
    run = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    h1 = json.loads((tmp_path / "one" / "history.json").read_text())
    h2 = json.loads((tmp_path / "two" / "history.json").read_text())
    assert len(h1["steps"]) == len(h2["steps"]) == 4
    for key in ("loss", "demix", "volume"):
        np.testing.assert_allclose([s[key] for s in h2["steps"]], [s[key] for s in h1["steps"]], rtol=1e-5, atol=1e-7)
    a, b = _state(tmp_path / "one"), _state(tmp_path / "two")
    for key in a:
        torch.testing.assert_close(a[key].float(), b[key].float(), rtol=1e-4, atol=1e-5, msg=key)


def test_cm2_train_runs_resumes_and_refuses_a_users_folder(tmp_path: Path):
    """`cm2 train CONFIG` writes the run, `--resume` continues it, and a folder that holds a
    user's files is refused (exit 2) unless --overwrite."""
    from typer.testing import CliRunner

    from cm2optics.cli import app

    runner = CliRunner()
    config = tiny(tmp_path / "run", epochs=1, val_volumes=0).save(tmp_path / "tiny.yaml")
    first = runner.invoke(app, ["train", str(config), "--max-steps", "1", "--json"])
    assert first.exit_code == 0, first.output
    resumed = runner.invoke(app, ["train", str(config), "--resume", "--json"])
    assert resumed.exit_code == 0, resumed.output
    assert (tmp_path / "run" / "weights").is_dir()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    other = tiny(mine, epochs=1, val_volumes=0).save(tmp_path / "other.yaml")
    refused = runner.invoke(app, ["train", str(other)])
    assert refused.exit_code == 2 and "out_dir" in refused.output
    assert (mine / "notes.txt").read_text() == "keep"
    missing = runner.invoke(app, ["train", str(tmp_path / "nope.yaml")])
    assert missing.exit_code == 2 and "nope.yaml" in missing.output


# ----------------------------------------------------------------------------- export
def test_exported_weights_of_a_stopped_run_load_and_give_the_checkpoints_outputs(tmp_path, monkeypatch):
    """`export_weights` of a run stopped after 2 steps: the folder passes its SHA-256 check at
    load, its network gives the checkpoint's outputs, the reference histogram is the one the run
    made at its start (carried by the checkpoint, not rendered again) and the card's hardware is
    the run's (1 thread), not the exporter's; a checkpoint of the older version without these
    facts still exports (histogram rendered, threads from the config)."""
    from cm2optics.recon.net import train as training
    from cm2optics.recon.net.data import PatchSource
    from cm2optics.recon.net.train import export_weights, make_net

    config = tiny(tmp_path / "run", epochs=1, val_volumes=0)
    assert train(config, max_steps=2)["stopped"]
    state = torch.load(tmp_path / "run" / "checkpoint.pt", map_location="cpu", weights_only=False)
    reference = training._histogram(PatchSource(config), config)
    np.testing.assert_array_equal(state["histogram"], reference)
    assert state["hardware"] == {"device": "cpu", "threads": 1, "processes": 1}

    def rendered(*args, **kwargs):
        raise AssertionError("the export rendered the reference volumes again")

    monkeypatch.setattr(training, "_histogram", rendered)
    torch.set_num_threads(2)  # the exporter's threads must not reach the card
    try:
        folder = export_weights(tmp_path / "run", tmp_path / "exported")
    finally:
        torch.set_num_threads(1)
    monkeypatch.undo()
    loaded = load_weights(folder)
    np.testing.assert_array_equal(loaded.histogram, reference)
    net, _ = make_net(config)
    net.load_state_dict(state["model"])
    net.eval()
    x = torch.rand(1, 9, 32, 32, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        for mine, theirs in zip(net(x), loaded.net(x), strict=True):
            torch.testing.assert_close(theirs, mine, rtol=0, atol=0)
    card = (folder / "MODEL_CARD.md").read_text()
    assert "- optimiser steps: 2" in card and "- patches seen: 4" in card
    assert "- hardware: CPU, 1 torch thread per process, 1 process" in card

    del state["histogram"], state["hardware"]  # as written by the previous version
    torch.save(state, tmp_path / "run" / "checkpoint.pt")
    old = load_weights(export_weights(tmp_path / "run", tmp_path / "exported-old"))
    np.testing.assert_array_equal(old.histogram, reference)
    assert (
        "- hardware: 1 torch thread per process (the config's threads)"
        in (tmp_path / "exported-old" / "MODEL_CARD.md").read_text()
    )
    with pytest.raises(CheckpointError, match="no checkpoint to export"):
        export_weights(tmp_path / "nowhere", tmp_path / "never")
    assert not (tmp_path / "never").exists()


def test_cm2_train_export_refuses_a_missing_checkpoint_and_a_users_folder(tmp_path: Path):
    """`cm2 train CONFIG --export DIR`: no checkpoint yet is one line (exit 2) and writes nothing;
    a folder holding a user's file is refused without --overwrite and kept with it; the run's
    own export folder may be written again."""
    from typer.testing import CliRunner

    from cm2optics.cli import app

    runner = CliRunner()
    config = tiny(tmp_path / "run", epochs=1, val_volumes=0).save(tmp_path / "tiny.yaml")
    weights = tmp_path / "w"
    missing = runner.invoke(app, ["train", str(config), "--export", str(weights)])
    assert missing.exit_code == 2 and "no checkpoint to export" in missing.output, missing.output
    assert "Traceback" not in missing.output and not weights.exists()
    assert runner.invoke(app, ["train", str(config), "--max-steps", "1"]).exit_code == 0
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    refused = runner.invoke(app, ["train", str(config), "--export", str(mine)])
    assert refused.exit_code == 2 and "--export" in refused.output and "--overwrite" in refused.output
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    forced = runner.invoke(app, ["train", str(config), "--export", str(mine), "--overwrite"])
    assert forced.exit_code == 0, forced.output
    assert (mine / "notes.txt").read_text() == "keep" and load_weights(mine).config.channels == 8
    for _ in range(2):  # a new folder, then again into the command's own folder
        exported = runner.invoke(app, ["train", str(config), "--export", str(weights)])
        assert exported.exit_code == 0, exported.output
    assert sorted(p.name for p in weights.iterdir() if not p.name.startswith(".")) == [
        "MODEL_CARD.md",
        "SHA256SUMS",
        "config.yaml",
        "model.safetensors",
    ]


def test_running_mean_of_the_loss_curve():
    from cm2optics.recon.net.train import running_mean

    np.testing.assert_allclose(running_mean(np.array([1.0, 2.0, 3.0, 4.0]), 2), [1.0, 1.5, 2.5, 3.5])
    np.testing.assert_allclose(running_mean(np.arange(10.0), 100), np.arange(10.0) / 2)
    assert running_mean(np.zeros(0), 5).shape == (0,)


# ----------------------------------------------------------------------------- ablations
@pytest.mark.parametrize("ablation", ["no-demix", "enhancement-only", "synthesis-only"])
def test_the_ablations_drop_their_part_and_still_train(ablation):
    """Each of the paper's ablations builds without its part (fewer parameters), gives volumes
    of the full network's shape and a finite loss whose gradient reaches every parameter; the
    full config keeps its hash (weights shipped before the option existed still load)."""
    from cm2optics.recon.net.loss import cm2net_loss
    from cm2optics.recon.net.train import make_net

    full = tiny_config()
    config = tiny_config(ablation=ablation)
    assert (
        config.hash() != full.hash()
        and full.hash() == NetConfig.from_dict({k: v for k, v in full.to_dict().items() if k != "ablation"}).hash()
    )
    net, _ = make_net(config)
    whole, _ = make_net(full)
    assert net.parameter_count() < whole.parameter_count()
    missing = {"no-demix": "demix", "enhancement-only": "synthesis", "synthesis-only": "enhance"}[ablation]
    assert getattr(net, missing) is None and getattr(whole, missing) is not None
    x = torch.rand(2, 9, 32, 32)
    demix, volume = net(x)
    assert volume.shape == (2, config.n_planes, 32, 32) and (demix is None) == (ablation == "no-demix")
    loss, parts = cm2net_loss(demix, volume, torch.rand(2, 9, 32, 32), torch.rand(volume.shape), config, 2)
    loss.backward()
    assert torch.isfinite(loss) and (float(parts["demix"]) == 0.0) == (ablation == "no-demix")
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_cm2_train_ablation_trains_in_its_own_folder_and_exports(tmp_path: Path):
    """`cm2 train CONFIG --ablation no-demix` writes <out_dir>-no-demix (the full run's folder is
    untouched), exports weights that load as the ablated network; a wrong name is one line."""
    from typer.testing import CliRunner

    from cm2optics.cli import app

    runner = CliRunner()
    config = tiny(tmp_path / "run", epochs=1, val_volumes=0).save(tmp_path / "tiny.yaml")
    done = runner.invoke(app, ["train", str(config), "--ablation", "no-demix", "--max-steps", "1", "--json"])
    assert done.exit_code == 0, done.output
    assert (tmp_path / "run-no-demix" / "checkpoint.pt").is_file() and not (tmp_path / "run").exists()
    weights = tmp_path / "w"
    exported = runner.invoke(app, ["train", str(config), "--ablation", "no-demix", "--export", str(weights)])
    assert exported.exit_code == 0, exported.output
    loaded = load_weights(weights)
    assert loaded.config.ablation == "no-demix" and loaded.net.demix is None
    wrong = runner.invoke(app, ["train", str(config), "--ablation", "no-refocus"])
    assert wrong.exit_code == 2 and "--ablation no-refocus" in wrong.output and "Traceback" not in wrong.output


def test_a_fine_tuning_on_the_same_views_takes_the_reference_histogram_of_its_init_weights(tmp_path):
    from cm2optics.recon.net.train import make_net
    from cm2optics.recon.net.weights import save_weights

    base = tiny(tmp_path / "base", val_volumes=0)
    marked = np.linspace(0.0, 2.0, 256) ** 2  # no run's views would give these quantiles
    save_weights(make_net(base)[0], base, tmp_path / "init", histogram=marked)
    same = base.with_changes(init_weights=str(tmp_path / "init"), seed=5, out_dir=str(tmp_path / "same"))
    other = same.with_changes(synth=base.synth.with_changes(peak_photons=200.0), out_dir=str(tmp_path / "other"))
    for config in (same, other):
        train(config, max_steps=1)
    histograms = [
        torch.load(tmp_path / n / "checkpoint.pt", weights_only=False)["histogram"] for n in ("same", "other")
    ]
    np.testing.assert_array_equal(histograms[0], marked)  # the same model and recipe: taken
    assert not np.allclose(histograms[1], marked)  # another recipe: rendered anew
