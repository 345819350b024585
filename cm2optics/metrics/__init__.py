"""Detection and localisation metrics of 3-D reconstructions of sparse emitters (numpy/scipy).

The paper's evaluation (Supplement 1): binarise with one global threshold (given, or F1-optimal
on a validation set), connected components, Hungarian matching gated at 2× the emitter
diameter, then recall, precision, F1, Jaccard and lateral/axial RMSE over true positives;
breakdowns by distance from the centre, density, depth and size (Fig. 6); recall/precision maps.

- :mod:`~cm2optics.metrics.detect`: components → emitters (centroids, sizes).
- :mod:`~cm2optics.metrics.match`: gated Hungarian matching.
- :mod:`~cm2optics.metrics.scores`: scores with defined empty cases, the F1-optimal threshold.
- :mod:`~cm2optics.metrics.breakdown`: Fig. 6 breakdowns and maps.
- :mod:`~cm2optics.metrics.plots`: figures. :mod:`~cm2optics.metrics.evaluate`: files in, JSON out.
- :mod:`~cm2optics.cli.evaluate`: ``cm2 evaluate``.
"""

from cm2optics.metrics.breakdown import BREAKDOWNS, breakdown, density_breakdown, detection_maps, merge_evaluations
from cm2optics.metrics.detect import detect_emitters, volume_emitters
from cm2optics.metrics.match import Matching, match_emitters
from cm2optics.metrics.scores import (
    Evaluation,
    MatchOptions,
    evaluate_volume,
    f1_optimal_threshold,
    pooled_scores,
    scores,
)

__all__ = [
    "BREAKDOWNS",
    "Evaluation",
    "MatchOptions",
    "Matching",
    "breakdown",
    "density_breakdown",
    "detect_emitters",
    "detection_maps",
    "evaluate_volume",
    "f1_optimal_threshold",
    "match_emitters",
    "merge_evaluations",
    "pooled_scores",
    "scores",
    "volume_emitters",
]
