"""Figures and the report of ``cm2 calibrate scan``: residuals before and after, the effects found.

No physics here: everything is computed by :mod:`cm2optics.calibrate`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from cm2optics.calibrate.lowrank_correction import LowRankCorrection
from cm2optics.calibrate.residual import ResidualAnalysis
from cm2optics.calibrate.scan import ScanCalibration
from cm2optics.formats.atomic import write_atomic, write_json_atomic
from cm2optics.reports.document import Report

__all__ = ["residual_montage", "unexplained_section", "write_calibration_documents", "write_calibration_report"]


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def residual_montage(before: ResidualAnalysis, after: ResidualAnalysis, path: Path, count: int = 4) -> None:
    """Data, residual before and residual after for the images with the largest misfit before."""
    order = np.argsort(np.nan_to_num(before.chi2, nan=-1.0))[::-1][:count]
    fig = Figure(figsize=(9, 2.6 * len(order)))
    for row, i in enumerate(order):
        data = before.model_counts[i] + before.residual_counts[i] - before.registration.dark_level
        limit = float(np.abs(before.residual_counts[i]).max()) or 1.0
        panels = (
            (data, "gray", None, f"data {before.files[i]}"),
            (before.residual_counts[i], "RdBu_r", limit, f"residual before (χ² {before.chi2[i]:.2f})"),
            (after.residual_counts[i], "RdBu_r", limit, f"residual after (χ² {after.chi2[i]:.2f})"),
        )
        for col, (image, cmap, lim, title) in enumerate(panels):
            ax = fig.add_subplot(len(order), 3, 3 * row + col + 1)
            ax.imshow(image, cmap=cmap, vmin=-lim if lim else None, vmax=lim)
            ax.set_title(title, fontsize=8)
            ax.set_axis_off()
    fig.tight_layout()
    _save(fig, path)


def _field_maps(before: ResidualAnalysis, after: ResidualAnalysis, path: Path) -> None:
    """Energy ratio data/model and centroid error against the source's field position."""
    fig = Figure(figsize=(10, 4))
    for col, (analysis, label) in enumerate(((before, "before"), (after, "after"))):
        ax = fig.add_subplot(1, 2, col + 1)
        used = analysis.used
        ratio = np.nanmean(np.where(used[:, None], analysis.energy_ratio, np.nan), axis=1)
        shift = np.nanmean(np.linalg.norm(analysis.centroid_error_px, axis=-1), axis=1)
        points = ax.scatter(
            analysis.positions_mm[used, 0],
            analysis.positions_mm[used, 1],
            c=ratio[used],
            s=20 + 60 * np.nan_to_num(shift[used]),
            cmap="coolwarm",
            vmin=0.8,
            vmax=1.2,
        )
        ax.set_title(f"{label}: energy ratio data/model (size: centroid error)", fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_aspect("equal")
        fig.colorbar(points, ax=ax, shrink=0.8)
    fig.tight_layout()
    _save(fig, path)


def _patterns(correction: LowRankCorrection, path: Path) -> None:
    """The correction's convolution kernels, one panel each."""
    fig = Figure(figsize=(2.6 * len(correction.kernels), 2.6))
    half = correction.kernels.shape[-1] // 2
    for k, pattern in enumerate(correction.kernels):
        ax = fig.add_subplot(1, len(correction.kernels), k + 1)
        limit = float(np.abs(pattern).max()) or 1.0
        extent = (-half - 0.5, half + 0.5, half + 0.5, -half - 0.5)
        # flipped: each pixel shows where the kernel moves a focus's light (row, col px)
        ax.imshow(pattern[::-1, ::-1], cmap="RdBu_r", vmin=-limit, vmax=limit, extent=extent)
        ax.set_title(f"kernel {k + 1} ({correction.explained_share[k]:.0%} of the residual)", fontsize=9)
        ax.set_xlabel("light moved by (col px)", fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def _correction_section(report: Report, result: ScanCalibration, folder: Path) -> None:
    """The low-rank correction, labelled non-physical, with its held-out error."""
    correction, summary = result.correction, result.document["correction"]
    correction.save(folder / "lowrank-correction.npz")
    _patterns(correction, folder / "correction_patterns.png")
    held = summary["held_out"]
    report.heading("Low-rank correction (non-physical)")
    report.paragraph(
        f"{summary['label']}. Rank {summary['rank']}: {summary['kernel_px']} × {summary['kernel_px']}-px convolution "
        f"kernels acting on every model focus, weights interpolated over the positions; saved as "
        f"lowrank-correction.npz. On positions held "
        f"out of its fit ({held['method']}; {held['images']} images): NMSE {held['nmse_before']:.4g} → "
        f"{held['nmse_after']:.4g} (noise floor {held['nmse_noise_floor']:.4g}), χ² {held['chi2_before']:.3g} → "
        f"{held['chi2_after']:.3g}."
    )
    report.figure("correction_patterns.png", "The correction's kernels (the share of the residual each removes)")


def write_calibration_documents(result, folder: str | Path) -> tuple[Path, dict]:
    """Create ``folder`` and write a calibration's ``calibration.json`` and ``corrected-design.yaml``
    (any result with ``document`` and ``corrected_design``); returns the folder and the document."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_json_atomic(folder / "calibration.json", result.document)
    result.corrected_design.save(folder / "corrected-design.yaml")
    return folder, result.document


def write_calibration_report(result: ScanCalibration, folder: str | Path) -> Path:
    """Write ``calibration.json``, ``corrected-design.yaml``, the figures and ``report.html``/``.md``
    into ``folder``; returns the HTML report's path."""
    folder, doc = write_calibration_documents(result, folder)
    residual_montage(result.before, result.after, folder / "residual_montage.png")
    _field_maps(result.before, result.after, folder / "field_maps.png")
    report = Report(f"Calibration of {doc['design']} against {doc['scan']}")
    report.paragraph(
        f"NMSE {doc['nmse_before']:.4g} → {doc['nmse_after']:.4g}; reduced χ² {doc['chi2_before']:.3g} → "
        f"{doc['chi2_after']:.3g} ({doc['noise_model']})."
    )
    report.heading("Effects found")
    rows = [[e["name"], e["parameters"], e["uncertainties"]] for e in doc["effects"]]
    report.table(["effect", "parameters", "± (1σ)"], rows or [["none", "—", "—"]])
    unexplained_section(report, doc["unexplained"], "data")
    report.figure("residual_montage.png", "Data and residuals before and after, images with the largest misfit")
    report.figure("field_maps.png", "Energy ratio and centroid error against field position, before and after")
    if result.correction is not None:
        _correction_section(report, result, folder)
    return report.write(folder)


def unexplained_section(report: Report, unexplained: list[dict], what: str) -> None:
    """The report's "Unexplained residual" heading and table (``what``: "data", "frame", …)."""
    report.heading("Unexplained residual")
    if unexplained:
        report.table(
            ["lenslets", "field (mm)", "depths (mm)", "energy fraction", "description"],
            [
                [u["lenslets"], u["field_mm"], u["depths_mm"], u["energy_fraction"], u["description"]]
                for u in unexplained
            ],
        )
    else:
        report.paragraph(f"None: the corrected model explains the {what} to the noise.")
