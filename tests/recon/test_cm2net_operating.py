"""CM²Net's operating threshold: the rule (highest validation F1 meeting a precision and a recall
bound, else the F1-optimal threshold), chosen on validation volumes and stored under the weights'
SHA-256, the default of the inference, and the test set's score at it beside the F1-optimal one.
Seconds."""

from __future__ import annotations

import json

import numpy as np
import pytest
from tiny_net import tiny

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.recon.compare import _at_operating_threshold, comparison_table
from cm2optics.recon.net.operating import (
    CANDIDATES,
    METADATA_KEY,
    OperatingThreshold,
    calibrate_threshold,
    choose_threshold,
)
from cm2optics.recon.net.train import make_net
from cm2optics.recon.net.weights import WeightsError, load_weights, save_weights, store_metadata

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# pooled validation scores against threshold: precision rises, recall falls
SWEEP = [
    {"threshold": 0.05, "recall": 0.85, "precision": 0.88, "f1": 0.8647},
    {"threshold": 0.10, "recall": 0.80, "precision": 0.93, "f1": 0.8601},
    {"threshold": 0.20, "recall": 0.75, "precision": 0.945, "f1": 0.8363},
    {"threshold": 0.30, "recall": 0.71, "precision": 0.96, "f1": 0.8163},
    {"threshold": 0.50, "recall": 0.40, "precision": 0.99, "f1": 0.5698},
]


def test_the_rule_takes_the_highest_f1_within_both_bounds_else_the_f1_optimal_threshold():
    chosen = choose_threshold(SWEEP[::-1], min_precision=0.94, min_recall=0.70)
    assert chosen.threshold == 0.20 and chosen.met and chosen.validation["precision"] == 0.945
    assert "precision ≥ 0.94 and recall ≥ 0.7" in chosen.rule and "none reached" not in chosen.rule
    # a recall floor above every qualifying candidate: the F1-optimal one, said so
    fallback = choose_threshold(SWEEP, min_precision=0.94, min_recall=0.80)
    assert fallback.threshold == 0.05 and not fallback.met and "F1-optimal" in fallback.rule
    # equal F1: the lower threshold
    tie = choose_threshold([{**SWEEP[2], "threshold": 0.4}, SWEEP[2]], min_precision=0.9, min_recall=0.7)
    assert tie.threshold == 0.20
    with pytest.raises(ValueError, match="empty"):
        choose_threshold([])
    again = OperatingThreshold.from_json(chosen.to_json())
    assert again == chosen and json.loads(chosen.to_json())["rule"] == chosen.rule
    with pytest.raises(ValueError, match="strictly between"):
        OperatingThreshold.from_json(json.dumps({**json.loads(chosen.to_json()), "threshold": 1.0}))


@pytest.fixture()
def weights(tmp_path):
    config = tiny()
    net, _ = make_net(config)
    return save_weights(net, config, tmp_path / "w")


def test_the_threshold_chosen_on_validation_volumes_is_stored_and_is_the_inference_default(weights):
    from cm2optics.recon.net.data import validation_volumes
    from cm2optics.recon.net.infer import reconstruct_with_net

    loaded = load_weights(weights)
    assert loaded.operating is None and loaded.threshold == loaded.config.detect_threshold
    card = (weights / "MODEL_CARD.md").read_text()
    chosen, sweep = calibrate_threshold(weights, n_volumes=1, log=lambda _: None)
    assert [s["threshold"] for s in sweep] == list(CANDIDATES) and chosen.threshold in CANDIDATES
    assert chosen.threshold == choose_threshold(sweep).threshold
    assert chosen.validation["n_volumes"] == 1 and chosen.validation["seed"] == loaded.config.seed + 7919
    loaded = load_weights(weights)  # the sums were rewritten: still verifies
    assert loaded.operating == chosen and loaded.threshold == chosen.threshold
    assert (weights / "MODEL_CARD.md").read_text() == card
    sample, imaging = next(validation_volumes(loaded.config, 1))
    assert reconstruct_with_net(sample.measurement, loaded, imaging.source).threshold == chosen.threshold
    assert reconstruct_with_net(sample.measurement, loaded, imaging.source, threshold=0.7).threshold == 0.7
    store_metadata(weights, {METADATA_KEY: json.dumps({"threshold": 0.3})})
    with pytest.raises(WeightsError, match=METADATA_KEY):
        load_weights(weights)


def test_a_test_run_is_also_scored_at_the_weights_operating_threshold(weights):
    """Three true emitters; the volume holds two of them at 0.8 and one at 0.2: at the stored 0.5
    recall is 2/3 and precision 1 (the F1-optimal threshold would keep all three)."""
    grid = VolumeGrid((5, 41, 41), (10.0, 4.0, 4.0))
    truth = Emitters(
        np.array([-40.0, 0.0, 40.0]), np.array([0.0, 20.0, -20.0]), np.zeros(3), np.full(3, 10.0), np.ones(3)
    )
    volume = np.zeros(grid.shape, np.float32)
    for x, y, value in zip(truth.x_um, truth.y_um, (0.8, 0.8, 0.2), strict=True):
        iy, ix = int(round(y / 4.0)) + 20, int(round(x / 4.0)) + 20
        volume[2, iy - 1 : iy + 2, ix - 1 : ix + 2] = value
    run = {"method": "net", "weights": str(weights)}
    assert _at_operating_threshold(run, [(volume, grid, truth)], grid) is None  # none stored yet
    assert _at_operating_threshold({"method": "fista"}, [(volume, grid, truth)], grid) is None
    stored = OperatingThreshold(0.5, 0.94, 0.7, True, {"precision": 0.95})
    store_metadata(weights, {METADATA_KEY: stored.to_json()})
    at = _at_operating_threshold(run, [(volume, grid, truth)], grid)
    assert at["threshold"] == 0.5 and (at["n_tp"], at["n_fp"], at["n_fn"]) == (2, 0, 1)
    assert at["precision"] == 1.0 and at["recall"] == pytest.approx(2 / 3) and at["f1"] == pytest.approx(0.8)
    entry = {"variant": "cm2net", "seconds_per_volume": 1.0, "iterations_mean": 1, "peak_rss_gib": 0.5}
    entry |= {k: 1.0 for k in ("recall", "precision", "f1", "jaccard", "rmse_lateral_um", "rmse_axial_um")}
    entry |= {"per_volume_sd": {}, "at_operating_threshold": at}
    summary = {"runs": {"cm2net": entry}, "grid": grid.to_dict(), "n_volumes": 1, "n_emitters": 3, "n_voxels": 8405}
    table = comparison_table(summary)
    assert "| cm2net at its weights' operating threshold 0.5 | 0.667 | 1.000 | 0.800 |" in table
    assert "operating threshold its weights carry" in table
