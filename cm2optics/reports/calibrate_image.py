"""Figures and the report of ``cm2 calibrate image``: the frame's residual before and after, the
effects found, the reconstructions with their detections before and after.

No physics here: everything is computed by :mod:`cm2optics.calibrate.image`.
"""

from __future__ import annotations

from pathlib import Path

from cm2optics.calibrate.image import ImageCalibration
from cm2optics.metrics.plots import plot_overlay
from cm2optics.reports.calibrate import residual_montage, unexplained_section, write_calibration_documents
from cm2optics.reports.document import Report

__all__ = ["write_image_report"]


def _score_rows(doc: dict) -> list[list[object]]:
    """Recall, precision, F1, TP/FP/FN and the localisation RMSE (µm), before and after."""

    def rmse(value: float | None) -> str:
        return "—" if value is None else f"{value:.1f}"

    return [
        [
            label,
            f"{doc[f'recall_{key}']:.3f}",
            f"{doc[f'precision_{key}']:.3f}",
            f"{doc[f'f1_{key}']:.3f}",
            f"{doc[f'n_tp_{key}']} / {doc[f'n_fp_{key}']} / {doc[f'n_fn_{key}']}",
            rmse(doc[f"rmse_lateral_um_{key}"]),
            rmse(doc[f"rmse_axial_um_{key}"]),
        ]
        for key, label in (("before", "nominal model"), ("after", "corrected model"))
    ]


def write_image_report(result: ImageCalibration, folder: str | Path) -> Path:
    """Write ``calibration.json``, ``corrected-design.yaml``, the figures and ``report.html``/``.md``
    into ``folder``; returns the HTML report's path."""
    folder, doc = write_calibration_documents(result, folder)
    residual_montage(result.before, result.after, folder / "residual_maps.png", count=1)
    for key in ("before", "after"):
        plot_overlay(
            result.volumes[key],
            result.evaluations[key],
            folder / f"detections_{key}.png",
            title=f"{'nominal' if key == 'before' else 'corrected'} model: {doc[f'n_tp_{key}']} TP, "
            f"{doc[f'n_fp_{key}']} FP, {doc[f'n_fn_{key}']} FN",
        )
    report = Report(f"Calibration of {doc['design']} against the beads frame {doc['frame']}")
    report.paragraph(
        f"{doc['emitters']} reference emitters, frame binned {doc['binning']}×. Frame residual: NMSE "
        f"{doc['nmse_before']:.4g} → {doc['nmse_after']:.4g}; reduced χ² {doc['chi2_before']:.3g} → "
        f"{doc['chi2_after']:.3g}. Effects from the {doc['effects_from']}."
    )
    report.heading("Effects")
    rows = [[e["name"], e["parameters"], e["uncertainties"] or "—"] for e in doc["effects"]]
    report.table(["effect", "parameters", "± (1σ)"], rows or [["none", "—", "—"]])
    report.heading("Reconstruction before and after")
    r = doc["reconstruction"]
    report.paragraph(
        f"FISTA ({r['max_iter']} iterations at most, ℓ1 {r['l1']:g}) with 3D-LSV models of rank {r['rank']} built from "
        "the calibration simulator's single-source images, nominal and corrected; each volume scored against the "
        "reference emitters at its own F1-optimal threshold (matches within 2× the bead diameter)."
    )
    report.table(
        ["model", "recall", "precision", "F1", "TP / FP / FN", "lateral RMSE µm", "axial RMSE µm"], _score_rows(doc)
    )
    report.figure(
        "detections_before.png", "Nominal model: maximum projections, matched (white), missed (red), false (yellow)"
    )
    report.figure("detections_after.png", "Corrected model: maximum projections, matched, missed, false")
    report.figure("residual_maps.png", "The frame, its residual against the nominal and the corrected model")
    unexplained_section(report, doc["unexplained"], "frame")
    return report.write(folder)
