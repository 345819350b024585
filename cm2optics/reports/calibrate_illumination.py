"""Figures and the report of ``cm2 calibrate illumination``: the measured and modelled maps, the
residuals before and after, the radial profiles and the effects found.

No physics here: everything is computed by :mod:`cm2optics.calibrate.illumination`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from cm2optics.calibrate.illumination import IlluminationCalibration
from cm2optics.formats.atomic import write_atomic
from cm2optics.reports.calibrate import write_calibration_documents
from cm2optics.reports.document import Report

__all__ = ["write_illumination_calibration_report"]


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def _maps(result: IlluminationCalibration, path: Path) -> None:
    """Data, model and normalised residual (data − model) / σ, before and after."""
    m = result.measured
    extent = (-m.half_mm, m.half_mm, -m.half_mm, m.half_mm)
    fig = Figure(figsize=(10, 6.4))
    for row, ((data, model, sigma), label) in enumerate(((result.before, "before"), (result.after, "after"))):
        top = float(np.nanmax(data))
        panels = (
            (m.grid(data), "viridis", (0, top), f"data (counts/px), offset fitted {label}"),
            (m.grid(model), "viridis", (0, top), f"model {label}"),
            (m.grid((data - model) / sigma), "RdBu_r", (-5, 5), f"(data − model)/σ {label}"),
        )
        for col, (image, cmap, (lo, hi), title) in enumerate(panels):
            ax = fig.add_subplot(2, 3, 3 * row + col + 1)
            shown = ax.imshow(image, cmap=cmap, vmin=lo, vmax=hi, origin="lower", extent=extent)
            fig.colorbar(shown, ax=ax, shrink=0.8)
            ax.set_title(title, fontsize=8)
            ax.set_xlabel("x (mm)", fontsize=7)
            ax.set_ylabel("y (mm)", fontsize=7)
    fig.tight_layout()
    _save(fig, path)


def _profiles(doc: dict, path: Path) -> None:
    """Mean counts per pixel in rings about the axis: data and model, before and after."""
    profile = doc["radial_profile"]
    r = np.asarray(profile["radius_mm"])
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot()
    for key, style in (("data", "k-"), ("model_before", "C1--"), ("model_after", "C0-")):
        values = np.array([np.nan if v is None else v for v in profile[key]])
        ax.plot(r, values, style, label=key.replace("_", " "))
    ax.set_xlabel("radius on the sample (mm)")
    ax.set_ylabel("mean counts per pixel")
    ax.legend()
    fig.tight_layout()
    _save(fig, path)


def write_illumination_calibration_report(result: IlluminationCalibration, folder: str | Path) -> Path:
    """Write ``calibration.json``, ``corrected-design.yaml``, ``maps.png``, ``profiles.png`` and
    ``report.html``/``.md`` into ``folder``; returns the HTML report's path."""
    folder, doc = write_calibration_documents(result, folder)
    _maps(result, folder / "maps.png")
    _profiles(doc, folder / "profiles.png")
    report = Report(f"Illumination calibration of {doc['design']} against {doc['map']}")
    cv = doc["uniformity_cv"]
    report.paragraph(
        f"NMSE {doc['nmse_before']:.4g} → {doc['nmse_after']:.4g}; reduced χ² {doc['chi2_before']:.3g} → "
        f"{doc['chi2_after']:.3g} ({doc['noise_model']}). Uniformity CV over the field: data {cv['data']:.3f} "
        f"(shot noise alone {cv['data_noise']:.3f}), model {cv['model_before']:.3f} → {cv['model_after']:.3f}."
    )
    report.heading("Effects found")
    rows = [[e["name"], e["unit"], e["parameters"], e["uncertainties"]] for e in doc["effects"]]
    report.table(["effect", "LED unit", "parameters", "± (1σ)"], rows or [["none", "—", "—", "—"]])
    reg = doc["registration"]
    report.paragraph(
        f"Registration: scale {reg['scale']:.4g} ± {reg['scale_stderr']:.2g} counts per (mW/mm²), offset "
        f"({reg['offset_x_mm']:.3f} ± {reg['offset_x_mm_stderr']:.3f}, {reg['offset_y_mm']:.3f} ± "
        f"{reg['offset_y_mm_stderr']:.3f}) mm."
    )
    report.heading("Unexplained residual")
    if doc["unexplained"]:
        report.table(
            ["field (mm)", "energy fraction", "description"],
            [[u["field_mm"], u["energy_fraction"], u["description"]] for u in doc["unexplained"]],
        )
    else:
        report.paragraph("None: the corrected model explains the map to the noise.")
    report.figure("maps.png", "Data, model and normalised residual, before (top) and after (bottom) the effects")
    report.figure("profiles.png", "Radial profiles of the measured and the modelled maps")
    return report.write(folder)
