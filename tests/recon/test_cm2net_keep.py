"""CM²Net's validation during training (``val_every``, ``val_mix_volumes``) and the weights a run
keeps (``keep_weights``: best, average): the config's rules and hash, a tiny run's scorings and
the weights it exports against those of its own checkpoints. Toy sizes: a few seconds."""

from __future__ import annotations

import pytest
import torch
from tiny_net import tiny

from cm2optics.recon.net.checkpoint import CheckpointError
from cm2optics.recon.net.config import ConfigError
from cm2optics.recon.net.train import BEST, CHECKPOINT, _keep_weights, export_weights, kept_weights, train
from cm2optics.recon.net.weights import load_weights

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MIX = dict(mix_forward_model="toy:gaussian", mix_fraction=0.5, mix_synth={"view_px": 48, "patches_per_volume": 2})


def test_validation_and_kept_weights_enter_the_hash_only_when_set_and_are_checked():
    plain = tiny()
    assert (
        plain.with_changes(val_every=0, keep_weights="last", keep_average=7, val_mix_volumes=0).hash() == plain.hash()
    )
    assert plain.with_changes(val_every=5).hash() != plain.hash()
    best = plain.with_changes(keep_weights="best")
    assert best.hash() != plain.hash() and best.with_changes(keep_average=7).hash() == best.hash()
    average = plain.with_changes(keep_weights="average")
    assert average.with_changes(keep_average=7).hash() != average.hash()
    assert tiny(**MIX, val_mix_volumes=1).hash() != tiny(**MIX).hash()
    for bad, match in [
        (dict(keep_weights="first"), "keep_weights"),
        (dict(keep_weights="best", val_volumes=0), "needs validation volumes"),
        (dict(val_mix_volumes=1), "needs a mixed source"),
        (dict(val_every=-1), "val_every"),
    ]:
        with pytest.raises(ConfigError, match=match):
            tiny(**bad)


def test_the_kept_weights_are_the_best_scorings_and_the_mean_of_the_last_ones(tmp_path):
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.BatchNorm1d(2))
    scores = {10: 0.2, 20: 0.5, 30: 0.4, 40: 0.5}  # step: score; the best is the first of the highest
    states = {}
    for kind, keep in (("best", 1), ("average", 2)):
        config = tiny(keep_weights=kind, keep_average=keep)
        history: dict = {}
        for step, score in scores.items():
            with torch.no_grad():
                for p in net.parameters():
                    p.add_(step)
            net[1].num_batches_tracked.fill_(step)
            states[step] = {k: v.clone() for k, v in net.state_dict().items()}
            _keep_weights(net, config, tmp_path, history, {"step": step, "score": score, "f1": score})
        state, facts = kept_weights(tmp_path, config)
        expected = (
            states[20]
            if kind == "best"
            else {
                k: (states[30][k] + states[40][k]) / 2 if v.is_floating_point() else states[40][k]
                for k, v in states[40].items()
            }
        )
        assert facts["record"]["step"] == (20 if kind == "best" else 40)
        for key, value in expected.items():
            torch.testing.assert_close(state[key], value, rtol=0, atol=1e-6, msg=key)
        with pytest.raises(CheckpointError, match="another config"):
            kept_weights(tmp_path, config.with_changes(seed=5))
    # a resumed run that scores step 30 again drops the later states it had kept
    config = tiny(keep_weights="average", keep_average=4)
    for step in (10, 20, 30, 40, 30):
        _keep_weights(net, config, tmp_path / "resumed", {}, {"step": step, "score": 0.1})
    assert [k["step"] for k in torch.load(tmp_path / "resumed" / "average.pt", weights_only=False)["states"]] == [
        10,
        20,
        30,
    ]
    assert kept_weights(tmp_path, tiny()) is None
    with pytest.raises(CheckpointError, match="no best weights kept yet"):
        kept_weights(tmp_path / "none", tiny(keep_weights="best"))


@pytest.mark.slow
def test_a_run_scores_every_n_steps_and_keeps_the_best_and_the_average_weights(tmp_path):
    # 2 volumes × 4 patches, batch 2: 4 steps; scored at steps 1, 2, 3 and at the epoch's end
    config = tiny(out_dir=str(tmp_path / "best"), val_every=1, keep_weights="best", val_mix_volumes=1, **MIX)
    train(config)
    state = torch.load(tmp_path / "best" / CHECKPOINT, map_location="cpu", weights_only=False)
    scorings = state["history"]["validations"]
    assert [v["step"] for v in scorings] == list(range(1, state["global_step"] + 1))
    for v in scorings:
        assert 0.0 <= v["f1_best"] <= 1 and 0.0 <= v["mix_f1_best"] <= 1 and "mix_val_loss" in v
        assert v["score"] == pytest.approx((v["f1_best"] + v["mix_f1_best"]) / 2)
    best = max(scorings, key=lambda v: v["score"])  # the first of the highest
    kept = torch.load(tmp_path / "best" / BEST, map_location="cpu", weights_only=False)
    assert kept["record"]["step"] == best["step"] == state["history"]["best"]["step"]
    final = load_weights(tmp_path / "best" / "weights")
    for key, value in final.net.state_dict().items():
        torch.testing.assert_close(value, kept["model"][key], rtol=0, atol=0, msg=key)
    assert "best validation score" in (tmp_path / "best" / "weights" / "MODEL_CARD.md").read_text()

    # the mean of the last two scorings' weights: those of the run stopped at step 3 and of step 4
    average = tiny(out_dir=str(tmp_path / "avg"), val_every=1, keep_weights="average", keep_average=2, epochs=1)
    stopped = average.with_changes(out_dir=str(tmp_path / "at3"))
    train(average)
    train(stopped, max_steps=3)
    at3 = torch.load(tmp_path / "at3" / CHECKPOINT, map_location="cpu", weights_only=False)["model"]
    at4 = torch.load(tmp_path / "avg" / CHECKPOINT, map_location="cpu", weights_only=False)["model"]
    exported = load_weights(tmp_path / "avg" / "weights").net.state_dict()
    for key, value in exported.items():
        expected = (at3[key] + at4[key]) / 2 if torch.is_floating_point(value) else at4[key]
        torch.testing.assert_close(value, expected, rtol=1e-6, atol=1e-7, msg=key)
    last = load_weights(export_weights(tmp_path / "avg", tmp_path / "last", keep="last")).net.state_dict()
    for key, value in last.items():
        torch.testing.assert_close(value, at4[key], rtol=0, atol=0, msg=key)
