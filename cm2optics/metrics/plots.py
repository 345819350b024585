"""Figures of an evaluation (PNG, written atomically): breakdowns as in the paper's Fig. 6,
recall/precision maps, maximum-intensity projections with true positives, misses and
false positives marked, and depth-coloured projections of several volumes side by side."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.formats.atomic import write_atomic
from cm2optics.metrics.breakdown import BREAKDOWNS
from cm2optics.metrics.scores import Evaluation

__all__ = ["depth_coded_mip", "plot_breakdowns", "plot_depth_mips", "plot_maps", "plot_overlay", "save_figure"]


def save_figure(figure: Any, path: str | Path, dpi: int = 110) -> Path:
    """Save a matplotlib figure as PNG atomically."""
    return write_atomic(Path(path), lambda tmp: figure.savefig(tmp, dpi=dpi, format="png", bbox_inches="tight"))


def _figure(*args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """A figure without pyplot (no global state, no GUI backend)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=kwargs.pop("figsize", None))
    return figure, figure.subplots(*args, **kwargs)


def _value(row: dict[str, Any], key: str, prefer_mean: bool) -> tuple[float, float]:
    """(value, error bar) of a breakdown row; NaN (not drawn) where nothing defines it: recall
    without true emitters, precision without detections, RMSE without true positives."""
    needs = {"recall": "n_true", "precision": "n_detected", "rmse_lateral_um": "n_tp", "rmse_axial_um": "n_tp"}
    if key in needs and row.get(needs[key], 1) == 0:
        return np.nan, 0.0
    if row.get("n_true", 0) + row.get("n_detected", 0) == 0:
        return np.nan, 0.0
    mean, sd = row.get(f"{key}_mean"), row.get(f"{key}_sd")
    if prefer_mean and mean is not None:
        return float(mean), float(sd or 0.0)
    value = row.get(key)
    return (np.nan, 0.0) if value is None else (float(value), 0.0)


def plot_breakdowns(
    breakdowns: dict[str, list[dict[str, Any]]],
    path: str | Path,
    *,
    title: str = "",
    labels: Sequence[str] | None = None,
) -> Path:
    """One panel per breakdown (``lateral_mm``, ``density``, ``depth_um``, ``size_um``): recall and
    precision (blue, left axis) and lateral/axial RMSE (orange, right axis) against the bin
    centre, with the per-volume sd as error bars where there are several volumes.

    ``breakdowns`` maps a name to the rows of :func:`~cm2optics.metrics.breakdown.breakdown`; to
    compare methods, pass ``{"lateral_mm": [rows_a, rows_b]}``-style lists of lists with ``labels``.
    """
    names = [n for n in ("lateral_mm", "density", "depth_um", "size_um") if n in breakdowns]
    if not names:
        raise ValueError("nothing to plot: no breakdowns given")
    fig, axes = _figure(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        series = breakdowns[name]
        groups = series if series and isinstance(series[0], list) else [series]
        twin = ax.twinx()
        for g, rows in enumerate(groups):
            tag = f" ({labels[g]})" if labels and g < len(labels) else ""
            style = ["-o", "--s", ":^", "-.v"][g % 4]
            centre = np.array([(r["low"] + r["high"]) / 2 for r in rows])
            for key, colour, axis in (
                ("recall", "tab:blue", ax),
                ("precision", "navy", ax),
                ("rmse_lateral_um", "tab:orange", twin),
                ("rmse_axial_um", "saddlebrown", twin),
            ):
                values = np.array([_value(r, key, True) for r in rows])
                axis.errorbar(
                    centre,
                    values[:, 0],
                    yerr=values[:, 1],
                    fmt=style,
                    color=colour,
                    ms=3,
                    lw=1,
                    capsize=2,
                    label=f"{key.replace('_um', '')}{tag}",
                )
        ax.set_ylim(0, 1.05)
        ax.set_ylabel("recall, precision", color="tab:blue")
        twin.set_ylabel("RMSE (µm)", color="tab:orange")
        unit = "emitters/mm²" if name == "density" else BREAKDOWNS[name].unit
        label = "density" if name == "density" else BREAKDOWNS[name].label
        ax.set_xlabel(f"{label} ({unit})")
        ax.grid(alpha=0.3)
    lines, texts = [], []
    for ax in (axes[0][0], fig.axes[-1]):
        h, t = ax.get_legend_handles_labels()
        lines += h
        texts += t
    fig.legend(lines, texts, loc="upper center", ncol=min(len(texts), 4), fontsize=7, bbox_to_anchor=(0.5, 1.12))
    if title:
        fig.suptitle(title, y=1.18)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_maps(maps: dict[str, Any], path: str | Path, *, title: str = "") -> Path:
    """Recall and precision maps (patches with nothing to measure left blank)."""
    fig, axes = _figure(1, 2, figsize=(9, 4))
    x, y = maps["x_edges_um"] / 1000.0, maps["y_edges_um"] / 1000.0
    for ax, key in zip(axes, ("recall", "precision"), strict=True):
        image = np.ma.masked_invalid(maps[key])
        mesh = ax.pcolormesh(x, y, image, vmin=0, vmax=1, cmap="viridis")
        ax.set_aspect("equal")
        ax.invert_yaxis()
        ax.set_title(f"{key} ({maps['patch_um']:g}-µm patches)")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        fig.colorbar(mesh, ax=ax, fraction=0.046)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_overlay(recon: np.ndarray, evaluation: Evaluation, path: str | Path, *, title: str = "") -> Path:
    """XY and XZ maximum-intensity projections of ``recon`` with true positives (white circles),
    misses (red circles) and false positives (yellow crosses)."""
    grid = evaluation.grid
    z, y, x = (grid.axis_um(a) / 1000.0 for a in range(3))
    t, d, m = evaluation.truth, evaluation.detected, evaluation.matching
    found, true_det = m.true_matched(), m.detected_matched()
    extent_xy = (x[0], x[-1], y[-1], y[0])
    extent_xz = (x[0], x[-1], z[0] * 1000.0, z[-1] * 1000.0)
    fig, axes = _figure(2, 1, figsize=(7, 9), gridspec_kw={"height_ratios": [3, 1.3]})
    axes[0].imshow(recon.max(axis=0), extent=extent_xy, cmap="magma", interpolation="nearest")
    axes[1].imshow(
        recon.max(axis=1), extent=extent_xz, cmap="magma", aspect="auto", origin="lower", interpolation="nearest"
    )
    for ax, tv, dv in ((axes[0], t.y_um / 1000.0, d.y_um / 1000.0), (axes[1], t.z_um, d.z_um)):
        for pick, colour, label in ((found, "white", "true positive"), (~found, "red", "missed")):
            ax.scatter(
                t.x_um[pick] / 1000.0, tv[pick], s=28, facecolors="none", edgecolors=colour, linewidths=0.8, label=label
            )
        ax.scatter(
            d.x_um[~true_det] / 1000.0,
            dv[~true_det],
            s=22,
            marker="x",
            color="yellow",
            linewidths=0.8,
            label="false positive",
        )
    axes[0].set_xlabel("x (mm)")
    axes[0].set_ylabel("y (mm)")
    axes[1].set_xlabel("x (mm)")
    axes[1].set_ylabel("z (µm), +z towards the device")
    axes[0].legend(loc="upper right", fontsize=7, framealpha=0.5)
    axes[0].set_title(title or f"threshold {evaluation.threshold:.4g}: {m.n_tp} TP, {m.n_fp} FP, {m.n_fn} FN")
    fig.tight_layout()
    return save_figure(fig, path)


def depth_coded_mip(volume: np.ndarray, *, vmax: float | None = None, cmap: str = "turbo") -> np.ndarray:
    """The depth-coloured maximum projection of a (z, y, x) volume along z: (y, x, 3) RGB in [0, 1]
    whose hue is the colour map at the plane of the maximum (plane 0 → 0, the last plane → 1)
    and whose brightness is that maximum ÷ ``vmax`` (default: the volume's maximum), clipped."""
    from matplotlib import colormaps

    volume = np.asarray(volume, float)
    if volume.ndim != 3 or volume.shape[0] < 1:
        raise ValueError(f"volume of shape {volume.shape}: need (z, y, x)")
    peak = volume.max(axis=0)
    scale = float(vmax) if vmax is not None else float(peak.max())
    colours = colormaps[cmap](np.linspace(0.0, 1.0, volume.shape[0]))[:, :3]
    brightness = np.clip(peak / scale, 0.0, 1.0) if scale > 0 else np.zeros_like(peak)
    return colours[volume.argmax(axis=0)] * brightness[..., None]


def plot_depth_mips(
    panels: Sequence[tuple[str, np.ndarray, Any, float | None]],
    path: str | Path,
    *,
    cmap: str = "turbo",
    title: str = "",
) -> Path:
    """Depth-coloured maximum projections side by side, one per (title, volume (z, y, x), its
    grid, vmax or None for its own maximum), with one colour bar of depth (µm, +z towards the
    device); the grids must share their depth axis. Every panel shows the smallest panel's field."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    z_um = panels[0][2].axis_um(0)
    half_mm = min(min(grid.shape[a] * grid.voxel_um[a] for a in (1, 2)) for _, _, grid, _ in panels) / 2000.0
    fig, axes = _figure(1, len(panels), figsize=(4.2 * len(panels) + 1.0, 4.4), squeeze=False)
    for ax, (name, volume, grid, vmax) in zip(axes[0], panels, strict=True):
        if not np.allclose(grid.axis_um(0), z_um):
            raise ValueError(f"{name}: its planes are not those of {panels[0][0]}")
        y, x = (grid.axis_um(a) / 1000.0 for a in (1, 2))
        ax.imshow(
            depth_coded_mip(volume, vmax=vmax, cmap=cmap),
            extent=(x[0], x[-1], y[-1], y[0]),
            interpolation="nearest",
        )
        ax.set_xlim(-half_mm, half_mm)
        ax.set_ylim(half_mm, -half_mm)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_facecolor("black")
    axes[0][0].set_ylabel("y (mm)")
    bar = fig.colorbar(
        ScalarMappable(Normalize(float(z_um[0]), float(z_um[-1])), cmap=cmap), ax=list(axes[0]), fraction=0.02
    )
    bar.set_label("depth z (µm), +z towards the device")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
