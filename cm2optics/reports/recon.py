"""The demo's reconstruction sections: a small synthetic volume made the paper's way,
reconstructed by the model-based baselines (3D-LSV FISTA, and the V1 paper's depth-wise LSI
ADMM) and evaluated; and CM²Net with the shipped weights beside FISTA on a measurement
simulated at the weights' own geometry."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.reports.document import Report

__all__ = ["add_baseline_section", "add_net_section"]

#: The demo's runs: the LSV model with FISTA, the V1 paper's LSI ADMM (short: a demo).
DEMO_RUNS = {
    "3D-LSV · FISTA": {"forward": "lsv", "method": "fista", "l1": 0.02, "max_iter": 30},
    "LSI · ADMM (V1)": {"forward": "lsi", "method": "admm", "l1": 0.02, "max_iter": 15},
}


def _measurement_figure(sample: dict[str, Any], rays: np.ndarray, view_px: int, path: Path) -> Path:
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from cm2optics.metrics.plots import save_figure

    figure = Figure(figsize=(10, 3.6))
    axes = figure.subplots(1, 3, gridspec_kw={"width_ratios": [1.5, 1, 1]})
    axes[0].imshow(sample["measurement"], cmap="gray")
    for r, c in rays:
        axes[0].add_patch(
            Rectangle((c - view_px / 2, r - view_px / 2), view_px, view_px, fill=False, color="tab:orange", lw=0.6)
        )
    axes[0].set_title("noisy measurement, nine views at the chief rays", fontsize=9)
    axes[1].imshow(sample["views"][4], cmap="gray")
    axes[1].set_title("central view (noisy)", fontsize=9)
    axes[2].imshow(sample["demixed"][4], cmap="gray")
    axes[2].set_title("its demixed ground truth", fontsize=9)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    figure.tight_layout()
    return save_figure(figure, path)


#: the columns of the baselines' table
_RUN_COLUMNS = [
    "model · method",
    "variant",
    "recall",
    "precision",
    "F1",
    "Jaccard",
    "lateral RMSE µm",
    "axial RMSE µm",
    "iterations",
    "time s",
    "memory est. GiB",
]


def _score_cells(m: dict) -> list:
    """Recall, precision, F1, Jaccard and the lateral/axial RMSE (µm) of one evaluation's metrics."""
    return [
        f"{m['recall']:.2f}",
        f"{m['precision']:.2f}",
        f"{m['f1']:.2f}",
        f"{m['jaccard']:.2f}",
        "—" if m["rmse_lateral_um"] is None else f"{m['rmse_lateral_um']:.1f}",
        "—" if m["rmse_axial_um"] is None else f"{m['rmse_axial_um']:.1f}",
    ]


def _run_row(name: str, m: dict, record: dict) -> list:
    """One run's row of the baselines' table: its scores (µm), iterations, seconds and memory (GiB)."""
    return [
        name,
        record["variant"],
        *_score_cells(m),
        record["iterations"],
        f"{record['seconds']:.1f}",
        f"{record['memory_estimate']['total_gib']:.2f}",
    ]


def add_baseline_section(
    report: Report,
    design: SystemDesign,
    model_path: str | Path | None,
    out_dir: str | Path,
    *,
    title: str | None = None,
) -> None:
    """Synthesise one small volume, reconstruct it with the baselines, evaluate, and report.

    model_path: an LSV model (``cm2 lsv build``); None or missing: a small analytic model of
    ``design`` is built into ``out_dir/baseline`` (binned 8×, seconds).
    """
    from cm2optics.metrics.plots import plot_overlay
    from cm2optics.recon.compare import demo_baselines

    folder = Path(out_dir) / "baseline"
    demo = demo_baselines(design, folder, model_path, DEMO_RUNS)
    config, grid, truth, sample = demo["config"], demo["grid"], demo["truth"], demo["sample"]
    origin, build_s, synth_s = demo["origin"], demo["build_s"], demo["synth_s"]
    _measurement_figure(sample, demo["chief_rays_px"], config.view_px, folder / "measurement.png")
    rows = []
    for name, run in DEMO_RUNS.items():
        result = demo["runs"][name]
        m, record = result["evaluation"].metrics, result["record"]
        plot_overlay(
            result["volume"],
            result["evaluation"],
            folder / f"overlay_{run['forward']}-{run['method']}.png",
            title=f"{name}: {m['n_tp']} TP, {m['n_fp']} FP, {m['n_fn']} FN",
        )
        rows.append(_run_row(name, m, record))
    report.heading(title or "Synthetic data and model-based baselines")
    report.paragraph(
        f"One volume made the paper's way at a scaled-down size with {origin} ({build_s:.1f} s): a {config.fov_mm[0]:g}-mm field, "
        f"{len(truth)} spherical emitters of 8–20 µm (drawn on a 5× finer grid and averaged down, intensity ∝ d²), "
        f"grid {' × '.join(map(str, grid.shape))} of {grid.voxel_um[1]:.1f} × {grid.voxel_um[2]:.1f} × {grid.voxel_um[0]:g} µm, "
        f"the measurement from the 3D-LSV model with Poisson (500 peak photons) and Gaussian (0.048 ± 0.017) noise, the nine "
        f"views cropped at the chief rays and their demixed ground truth, {config.patches_per_volume} training patches — "
        f"{synth_s:.1f} s. Full-size sets: `cm2 synth --model MODEL`."
    )
    report.figure(
        "baseline/measurement.png",
        "Synthetic measurement with the nine views, and the central view with its demixed ground truth",
    )
    report.paragraph(
        "Reconstructed with the 3D-LSV model (FISTA, non-negativity + ℓ1) and with the V1 paper's depth-wise LSI model "
        "(its closed-form ADMM), each binarised at its own F1-optimal threshold, connected components matched to the true "
        "emitters by the Hungarian algorithm within 2× their diameter (`cm2 reconstruct`, `cm2 evaluate`)."
    )
    report.table(_RUN_COLUMNS, rows)
    for name, run in DEMO_RUNS.items():
        report.figure(
            f"baseline/overlay_{run['forward']}-{run['method']}.png",
            f"{name}: maximum projections, matched (white), missed (red), false (yellow)",
        )


#: the columns of the CM²Net section's table
_NET_COLUMNS = [
    "method",
    "recall",
    "precision",
    "F1",
    "Jaccard",
    "lateral RMSE µm",
    "axial RMSE µm",
    "threshold",
    "time s",
]


def add_net_section(
    report: Report,
    out_dir: str | Path,
    *,
    weights: str | Path | None = None,
    title: str | None = None,
    fov_mm: float = 0.6,
    view_px: int = 192,
) -> dict[str, Any] | None:
    """CM²Net with the shipped weights (or ``weights``) beside FISTA on one measurement simulated
    at the weights' own geometry (:func:`cm2optics.recon.compare.demo_net`): depth-coloured
    maximum projections (net | FISTA | ground truth) as ``out_dir/net/mips.png`` and a metrics
    table. fov_mm: the simulated field (mm); view_px: the side of the views (px). Without the
    weights folder, or with one that fails its checks, the section says so in one line. Returns
    the comparison (None without usable weights)."""
    from cm2optics.metrics.plots import plot_depth_mips
    from cm2optics.recon.compare import demo_net
    from cm2optics.recon.net.weights import WeightsError, shipped_weights
    from cm2optics.synth.raster import rasterize_balls

    folder = Path(weights) if weights is not None else shipped_weights()
    report.heading(title or "CM²Net")
    if not folder.is_dir():
        report.paragraph(
            f"No trained CM²Net weights at `{folder}`: this section needs them (a clone of the repository ships "
            "them in `reconstruction/cm2net-cpu`; `cm2 train CONFIG --export DIR` writes them from a run)."
        )
        return None
    try:
        demo = demo_net(folder, fov_mm=fov_mm, view_px=view_px)
    except WeightsError as error:  # e.g. a clone without the Git LFS objects: the rest of the demo still stands
        report.paragraph(f"The CM²Net weights at `{folder}` cannot be used: {error}")
        return None
    config, grid, truth, runs, seconds = demo["config"], demo["grid"], demo["truth"], demo["runs"], demo["seconds"]
    loaded = demo["weights"]
    net, fista = runs["net"], runs["fista"]
    truth_volume = rasterize_balls(truth, grid, supersample=config.supersample)
    plot_depth_mips(
        [
            ("CM²Net (probability)", net["volume"], net["grid"], 1.0),
            (f"FISTA, {fista['record']['iterations']} iterations", fista["volume"], grid, None),
            (f"ground truth, {len(truth)} emitters", truth_volume, grid, None),
        ],
        Path(out_dir) / "net" / "mips.png",
    )
    rows = []
    for name, run, s in (("CM²Net", net, seconds["net"]), ("3D-LSV · FISTA", fista, seconds["fista"])):
        evaluation = run["evaluation"]
        rows.append([name, *_score_cells(evaluation.metrics), f"{evaluation.threshold:.3g}", f"{s:.1f}"])
    report.paragraph(
        f"The weights in `{loaded.folder}` ({loaded.config.channels} channels, {loaded.config.blocks} blocks, "
        f"{loaded.net.parameter_count():,} parameters; its training is in its `MODEL_CARD.md`) on one measurement simulated at "
        f"their own geometry: their forward model `{loaded.config.forward_model}` and grid "
        f"({grid.shape[0]} planes of {grid.voxel_um[0]:g} µm, {grid.voxel_um[1]:g}-µm voxels), their recipe on a "
        f"{config.fov_mm[0]:g}-mm disc ({len(truth)} emitters of {config.diameter_um[0]:g}–{config.diameter_um[1]:g} µm, "
        f"{demo['sample'].draw.density_per_mm2:.0f} per mm², {config.noise} noise), test seed {demo['seed']} (no training volume "
        f"used it), on the {demo['sensor_shape'][0]} × {demo['sensor_shape'][1]}-px sensor window that holds the "
        f"nine {config.view_px}-px views — {seconds['model'] + seconds['simulate']:.1f} s. Reconstructed in one pass "
        f"by the network and by FISTA through the same model (non-negativity + ℓ1, no model mismatch: the model that "
        f"made the data), each binarised at its own F1-optimal threshold and matched as `cm2 evaluate` does; one "
        f"torch thread."
    )
    report.figure(
        "net/mips.png",
        "Depth-coloured maximum projections along z: CM²Net | FISTA | ground truth (hue: depth of the brightest "
        "voxel; brightness: its value)",
    )
    report.table(_NET_COLUMNS, rows)
    return demo
