"""Evaluate a reconstruction file against a ground-truth file (what ``cm2 evaluate`` runs).

The ground truth is an emitter CSV (preferred: exact centres and diameters) or a ground-truth
volume on the same grid as the reconstruction (its connected components are the emitters; an
emitter's diameter is then estimated from its component). Without a threshold, the F1-optimal
one on this very pair is used and reported as such: an optimistic choice, fair only when the
same rule is applied to every method compared (give ``threshold`` from a validation set
otherwise).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.formats.emitters import Emitters, read_emitters
from cm2optics.formats.volume import VolumeGrid, read_volume
from cm2optics.metrics.breakdown import BREAKDOWNS, breakdown, detection_maps
from cm2optics.metrics.detect import volume_emitters
from cm2optics.metrics.scores import Evaluation, MatchOptions, evaluate_volume, f1_optimal_threshold

__all__ = ["evaluate_files", "load_truth", "summary"]


def load_truth(path: str | Path, grid: VolumeGrid, voxel_um: tuple[float, float, float] | None = None) -> Emitters:
    """Ground-truth emitters from a CSV, or from a volume file on ``grid``."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return read_emitters(path)
    volume, gt_grid = read_volume(
        path, voxel_um if voxel_um is not None else (grid.voxel_um if path.suffix.lower() == ".npy" else None)
    )
    if gt_grid.shape != grid.shape or not np.allclose(gt_grid.voxel_um, grid.voxel_um, rtol=1e-4):
        raise ValueError(
            f"{path}: the ground-truth volume's grid {gt_grid.shape} × {_fmt(gt_grid.voxel_um)} µm does not match the "
            f"reconstruction's {grid.shape} × {_fmt(grid.voxel_um)} µm"
        )
    return volume_emitters(volume, grid)


def _fmt(voxel: tuple[float, ...]) -> str:
    return "×".join(f"{v:g}" for v in voxel)


def density_per_mm2(truth: Emitters, grid: VolumeGrid) -> float:
    """True emitters per mm² of the volume's lateral extent."""
    area = grid.shape[1] * grid.voxel_um[1] * grid.shape[2] * grid.voxel_um[2] / 1e6
    return len(truth) / area if area > 0 else 0.0


def summary(evaluation: Evaluation, *, patch_um: float = 250.0, maps: bool = True) -> dict[str, Any]:
    """The JSON-ready record of one evaluation: scores, threshold, breakdowns, maps."""
    out: dict[str, Any] = dict(evaluation.metrics)
    out["threshold"] = evaluation.threshold
    out["density_per_mm2"] = round(density_per_mm2(evaluation.truth, evaluation.grid), 3)
    out["breakdowns"] = {name: breakdown(evaluation, name) for name in BREAKDOWNS}
    if maps:
        m = detection_maps(evaluation, patch_um)
        out["maps"] = {
            "patch_um": m["patch_um"],
            "x_edges_um": m["x_edges_um"].tolist(),
            "y_edges_um": m["y_edges_um"].tolist(),
            "recall": _nan_to_none(m["recall"]),
            "precision": _nan_to_none(m["precision"]),
        }
    return out


def _nan_to_none(array: np.ndarray) -> list:
    return [[None if not math.isfinite(v) else round(float(v), 6) for v in row] for row in array]


def evaluate_files(
    recon_path: str | Path,
    truth_path: str | Path,
    *,
    threshold: float | None = None,
    options: MatchOptions | None = None,
    voxel_um: tuple[float, float, float] | None = None,
    patch_um: float = 250.0,
    out_dir: str | Path | None = None,
    plots: bool = True,
    validation: list[tuple[str | Path, str | Path]] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Evaluate ``recon_path`` against ``truth_path``; with ``out_dir`` write ``metrics.json`` and
    (``plots``) ``breakdowns.png``, ``maps.png``, ``overlay.png`` there. Returns the summary.

    threshold: the global threshold; None: the F1-optimal one on ``validation`` (pairs of
    reconstruction and truth files), or without it on the evaluated pair itself."""
    options = options or MatchOptions()
    recon, grid = read_volume(recon_path, voxel_um, require_3d=True)
    truth = load_truth(truth_path, grid, voxel_um)
    if threshold is None and validation:
        pairs = []
        for v_recon, v_truth in validation:
            v_volume, v_grid = read_volume(v_recon, voxel_um, require_3d=True)
            pairs.append((v_volume, v_grid, load_truth(v_truth, v_grid, voxel_um)))
        threshold, sweep = f1_optimal_threshold(pairs, options, progress=progress)
        source = f"F1-optimal on {len(pairs)} validation pair(s)"
    elif threshold is None:
        threshold, sweep = f1_optimal_threshold([(recon, grid, truth)], options, progress=progress)
        source = "F1-optimal on the evaluated pair"
    else:
        if not math.isfinite(threshold):
            raise ValueError(f"--threshold = {threshold}: must be a finite number")
        sweep, source = None, "given"
    evaluation = evaluate_volume(recon, grid, truth, threshold, options)
    result = summary(evaluation, patch_um=patch_um)
    result["threshold_source"] = source
    if sweep is not None:
        result["threshold_sweep"] = sweep
    result["gate_factor"] = options.gate_factor
    result["min_gate_um"] = options.floor_um(grid)
    result["connectivity"] = options.connectivity
    result["reconstruction"] = str(recon_path)
    result["ground_truth"] = str(truth_path)
    result["grid"] = grid.to_dict()
    if out_dir is not None:
        from cm2optics.formats.atomic import write_json_atomic
        from cm2optics.metrics.plots import plot_breakdowns, plot_maps, plot_overlay

        out_dir = Path(out_dir)
        figures = {}
        if plots:
            name = Path(recon_path).name
            figures["breakdowns"] = str(plot_breakdowns(result["breakdowns"], out_dir / "breakdowns.png", title=name))
            figures["maps"] = str(plot_maps(detection_maps(evaluation, patch_um), out_dir / "maps.png", title=name))
            figures["overlay"] = str(plot_overlay(recon, evaluation, out_dir / "overlay.png"))
        result["figures"] = figures
        write_json_atomic(out_dir / "metrics.json", result)
    return result
