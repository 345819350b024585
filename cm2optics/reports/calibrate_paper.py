"""The report of ``cm2 calibrate paper``: the excitation-power chain as a table and a figure.

No physics here: everything is computed by :mod:`cm2optics.calibrate.paper`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from cm2optics.formats.atomic import write_atomic, write_json_atomic
from cm2optics.reports.document import Report

__all__ = ["write_paper_report"]


def _chain_figure(power: dict[str, Any], path: Path) -> None:
    """The power after each factor of the chain (log scale), the measurement as a line."""
    names = ["traced"] + [f["name"] for f in power["factors"]]
    values = [power["predicted_mw"]]
    for factor in power["factors"]:
        values.append(values[-1] * factor["value"])
    fig = Figure(figsize=(8, 4))
    ax = fig.add_subplot()
    ax.bar(np.arange(len(values)), values, color=["C0"] + ["C1" if f["computed"] else "C7" for f in power["factors"]])
    ax.axhline(power["measured_mw"], color="k", ls="--", label=f"measured {power['measured_mw']:g} mW")
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(values)), names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("excitation power in the field (mW)")
    ax.set_title("after each factor (orange: computed, grey: assumed)", fontsize=9)
    ax.legend()
    fig.tight_layout()
    FigureCanvasAgg(fig)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def write_paper_report(document: dict[str, Any], folder: str | Path) -> Path:
    """Write ``paper.json``, ``excitation_power.png`` and ``report.html``/``.md``; returns the HTML's path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_json_atomic(folder / "paper.json", document)
    power = document["excitation_power"]
    _chain_figure(power, folder / "excitation_power.png")
    report = Report(f"The paper's measurements against {power['setup']['design']}")
    report.heading("(a) Excitation power")
    report.paragraph(
        f"Measured {power['measured_mw']:g} mW ({power['measured_source']}); traced {power['predicted_mw']:.1f} ± "
        f"{power['predicted_stderr_mw']:.1f} mW ({power['predicted_ratio']:.2f}×). {power['description']}."
    )
    report.table(
        ["factor", "value", "± (1σ, relative)", "computed", "source"],
        [
            [f["name"], f["value"], f["uncertainty"], "yes" if f["computed"] else "assumed", f["source"]]
            for f in power["factors"]
        ],
    )
    report.figure("excitation_power.png", "The traced power after each factor of the chain, against the measurement")
    return report.write(folder)
