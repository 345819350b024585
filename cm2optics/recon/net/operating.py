"""The weights' operating threshold: chosen on validation volumes for a stated rule, stored with them.

The paper scores CM²Net at the global threshold that maximises F1 *on the test set itself*
(Section 3.1, after Bao et al. 2021), and so do ``cm2 net-testset`` and ``cm2 evaluate``: that is a
score, not an operating point — a measurement to reconstruct comes without ground truth. The
operating threshold is chosen once, on full-field validation volumes (the run's validation seed,
never a test set's), by one rule: among the candidate thresholds (:data:`CANDIDATES`) whose pooled
validation precision is ≥ ``min_precision`` and recall ≥ ``min_recall``, the one with the highest
F1; when none qualifies, the F1-optimal candidate, recorded with ``met: false``. It is stored in
``model.safetensors``' metadata (:data:`METADATA_KEY`, under the SHA-256), is the default detection
threshold of :func:`~cm2optics.recon.net.infer.reconstruct_with_net` (``cm2 reconstruct --method
net``), and ``cm2 net-testset`` scores the network at it beside the F1-optimal threshold.

Run after the lateral calibration (detections move with it)::

    python -m cm2optics.recon.net.operating reconstruction/cm2net-cpu-traced --n-volumes 4
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CANDIDATES", "METADATA_KEY", "OperatingThreshold", "calibrate_threshold", "choose_threshold"]

#: Metadata key of the operating threshold in ``model.safetensors``.
METADATA_KEY = "operating_threshold"
#: Candidate thresholds on the sigmoid output: 40 geometrically spaced from 0.01 to 0.95.
CANDIDATES = tuple(float(t) for t in np.round(np.geomspace(0.01, 0.95, 40), 5))
#: The issue's targets (the paper's averages): precision ≥ 0.94 at recall ≥ 0.70.
MIN_PRECISION, MIN_RECALL = 0.94, 0.70


@dataclass(frozen=True)
class OperatingThreshold:
    """threshold: on the sigmoid output [0, 1]; met: whether a candidate reached both bounds
    (else the F1-optimal one); validation: its pooled scores and where they come from."""

    threshold: float
    min_precision: float
    min_recall: float
    met: bool
    validation: dict[str, Any] = field(default_factory=dict)

    @property
    def rule(self) -> str:
        return f"highest validation F1 with precision ≥ {self.min_precision:g} and recall ≥ {self.min_recall:g}" + (
            "" if self.met else " (none reached it: the F1-optimal threshold)"
        )

    def to_json(self) -> str:
        return json.dumps({**asdict(self), "rule": self.rule})

    @classmethod
    def from_json(cls, text: str) -> OperatingThreshold:
        data = json.loads(text)
        threshold = float(data["threshold"])
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"operating threshold {threshold}: must lie strictly between 0 and 1")
        return cls(
            threshold, float(data["min_precision"]), float(data["min_recall"]), bool(data["met"]), data["validation"]
        )


def choose_threshold(
    sweep: list[dict[str, float]], min_precision: float = MIN_PRECISION, min_recall: float = MIN_RECALL
) -> OperatingThreshold:
    """The rule of the module docstring on a sweep of pooled validation scores, one dict per
    candidate (``threshold``, ``recall``, ``precision``, ``f1``); ties go to the lower threshold."""
    if not sweep:
        raise ValueError("an empty sweep: score at least one candidate threshold")
    ordered = sorted(sweep, key=lambda s: s["threshold"])
    qualified = [s for s in ordered if s["precision"] >= min_precision and s["recall"] >= min_recall]
    pool = qualified or ordered
    best = max(pool, key=lambda s: (s["f1"], -s["threshold"]))
    return OperatingThreshold(best["threshold"], min_precision, min_recall, bool(qualified), dict(best))


def calibrate_threshold(
    folder: str | Path,
    *,
    n_volumes: int = 4,
    min_precision: float = MIN_PRECISION,
    min_recall: float = MIN_RECALL,
    log=print,
) -> tuple[OperatingThreshold, list[dict[str, float]]]:
    """Choose the operating threshold of the weights in ``folder`` on ``n_volumes`` full-field
    validation volumes (reconstructed with the weights' lateral correction) and store it in their
    ``model.safetensors`` (the SHA-256 sums rewritten; card and config untouched). Returns it and
    the sweep of pooled validation scores."""
    from cm2optics.metrics import evaluate_volume, pooled_scores
    from cm2optics.recon.net.data import VALIDATION_SEED_OFFSET, validation_volumes
    from cm2optics.recon.net.infer import reconstruct_with_net
    from cm2optics.recon.net.weights import load_weights, store_metadata

    loaded = load_weights(folder)
    pairs = []
    for index, (sample, imaging) in enumerate(validation_volumes(loaded.config, n_volumes)):
        result = reconstruct_with_net(sample.measurement, loaded, imaging.source)
        pairs.append((result.volume, result.grid, sample.draw.emitters))
        log(f"validation volume {index + 1}/{n_volumes}: {len(sample.draw.emitters)} emitters")
    sweep = []
    for t in CANDIDATES:
        pooled = pooled_scores([evaluate_volume(v, g, truth, t) for v, g, truth in pairs])
        sweep.append({"threshold": t, **{k: pooled[k] for k in ("recall", "precision", "f1", "n_tp", "n_fp", "n_fn")}})
    chosen = choose_threshold(sweep, min_precision, min_recall)
    validation = {
        **chosen.validation,
        "seed": loaded.config.seed + VALIDATION_SEED_OFFSET,
        "n_volumes": n_volumes,
        "n_emitters": int(sum(len(t) for _, _, t in pairs)),
    }
    chosen = OperatingThreshold(chosen.threshold, min_precision, min_recall, chosen.met, validation)
    store_metadata(folder, {METADATA_KEY: chosen.to_json()})
    return chosen, sweep


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m cm2optics.recon.net.operating", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("weights", help="weights folder, e.g. reconstruction/cm2net-cpu (rewritten in place)")
    parser.add_argument("--n-volumes", type=int, default=4)
    parser.add_argument("--min-precision", type=float, default=MIN_PRECISION)
    parser.add_argument("--min-recall", type=float, default=MIN_RECALL)
    args = parser.parse_args(argv)
    chosen, sweep = calibrate_threshold(
        args.weights, n_volumes=args.n_volumes, min_precision=args.min_precision, min_recall=args.min_recall
    )
    print(json.dumps({"operating_threshold": json.loads(chosen.to_json()), "sweep": sweep}, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
