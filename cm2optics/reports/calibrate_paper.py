"""The report of ``cm2 calibrate paper``: (a) the excitation-power chain, (b) the phantom's SBR
terms, (c) the magnification and the edge drop, as tables and figures.

No physics here: everything is computed by :mod:`cm2optics.calibrate.paper`,
:mod:`~cm2optics.calibrate.paper_sbr` and :mod:`~cm2optics.calibrate.paper_field`.
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


def _sbr_figure(sbr: dict[str, Any], path: Path) -> None:
    """Left: each background term per pixel against the bead's peak, per chain (log scale).
    Right: the gain against the resin's autofluorescence, the measurement as a line."""
    fig = Figure(figsize=(10, 4))
    left, right = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    names = ["signal", "leakage", "beads", "autofluorescence"]
    x = np.arange(len(names))
    for shift, (chain, terms) in zip((-0.2, 0.2), sbr["per_pixel_per_excitation_photon"].items(), strict=True):
        left.bar(x + shift, [terms[n] for n in names], width=0.4, label=chain.replace("_", " "))
    left.set_yscale("log")
    left.set_xticks(x, ["bead peak", "leakage", "beads' wings", "resin autofl."], fontsize=8)
    left.set_ylabel("photoelectrons per pixel per excitation photon")
    left.set_title("signal and background per pixel (nominal parameters)", fontsize=9)
    left.legend(fontsize=8)
    curve = sbr["gain_vs_autofluorescence"]
    right.semilogx(curve["per_mm"], curve["gain"], "C0", label="model: leakage + beads + resin")
    right.axhline(sbr["measured_gain"], color="k", ls="--", label=f"measured > {sbr['measured_gain']:g}×")
    low, high = sbr["assumptions"]["resin_autofluorescence_per_mm"]["range"]
    right.axvspan(low, high, color="C7", alpha=0.2, label="assumed range")
    right.set_xlabel("resin autofluorescence (in-band photons / excitation photon / mm)", fontsize=8)
    right.set_ylabel("SBR gain of the hybrid filter")
    right.legend(fontsize=8)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def _field_figure(mag: dict[str, Any], edge: dict[str, Any], path: Path) -> None:
    """Left: the central focus's energy against the source's radius, three source profiles and the
    paper's drop. Right: the traced local magnification against radius, first order and the paper's."""
    fig = Figure(figsize=(10, 4))
    left, right = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    r = edge["radii_mm"]
    left.plot(r, edge["relative_energy_isotropic"], "C0o-", ms=3, label="isotropic source (optics only)")
    left.plot(
        r,
        edge["relative_energy_library_pinhole"],
        "C1s-",
        ms=3,
        label=f"pinhole {edge['library_pinhole_half_angle_deg']:g}°",
    )
    left.plot(
        r, edge["relative_energy_fitted"], "C2^-", ms=3, label=f"fitted {edge['source_profile_half_angle_deg']:g}°"
    )
    left.errorbar(
        [edge["paper_edge_radius_mm"]],
        [1 - edge["paper_drop"]],
        yerr=[edge["paper_drop_uncertainty"]],
        fmt="kD",
        label=f"paper: ≈ {100 * edge['paper_drop']:.0f} % drop",
    )
    left.set_xlabel("source radius (mm)")
    left.set_ylabel("central focus energy / on axis")
    left.legend(fontsize=8)
    right.plot(
        mag["traced_radii_mm"], mag["traced_local_magnification"], "C0o-", ms=3, label="traced (centroid / radius)"
    )
    right.axhline(mag["traced_magnification"], color="C0", ls=":", label="traced, least squares")
    right.axhline(mag["chief_ray_magnification"], color="C1", ls="-.", label="first order (chief ray)")
    right.axhline(
        mag["paper_magnification"], color="k", ls="--", label=f"paper ({mag['paper_object_pixel_um']:g}-µm pixel)"
    )
    right.set_xlabel("source radius (mm)")
    right.set_ylabel("|magnification|")
    right.legend(fontsize=8)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))


def _sbr_section(report: Report, sbr: dict[str, Any]) -> None:
    report.heading("(b) The hybrid filter's SBR gain on the bead phantom")
    report.paragraph(f"Measured > {sbr['measured_gain']:g}× ({sbr['measured_source']}). {sbr['description']}.")
    report.table(
        ["background terms", "SBR gain"],
        [[name.replace("+", " + "), value] for name, value in sbr["gain_by_terms"].items()],
    )
    report.table(
        ["chain", *sbr["sbr"]["hybrid"].keys()],
        [[chain.replace("_", " "), *values.values()] for chain, values in sbr["sbr"].items()],
    )
    report.table(
        ["parameter", "nominal", "range", "unit", "source"],
        [[k, a["value"], a.get("range", ""), a.get("unit", ""), a["source"]] for k, a in sbr["assumptions"].items()]
        + [[k, a["value"], a.get("range", ""), "paper", a["source"]] for k, a in sbr["paper_inputs"].items()],
    )
    report.figure(
        "sbr_phantom.png", "Signal and background terms per pixel; the gain against the resin's autofluorescence"
    )


def _field_section(report: Report, mag: dict[str, Any], edge: dict[str, Any]) -> None:
    report.heading("(c) De-magnification and the edge drop")
    report.paragraph(f"Paper: {mag['paper_object_pixel_source']}. {mag['description']}.")
    report.table(
        ["magnification", "value", "object pixel (µm)"],
        [
            [
                "paraxial",
                mag["paraxial_magnification"],
                round(mag["sensor_pixel_um"] / mag["paraxial_magnification"], 3),
            ],
            ["chief ray at best focus", mag["chief_ray_magnification"], mag["chief_ray_object_pixel_um"]],
            ["traced (least squares over the field)", mag["traced_magnification"], mag["traced_object_pixel_um"]],
            ["paper", mag["paper_magnification"], mag["paper_object_pixel_um"]],
        ],
    )
    report.paragraph(f"Paper: {edge['paper_drop_source']}. {edge['description']}.")
    report.figure("edge_drop.png", "Central focus energy and local magnification against the source's radius")


def write_paper_report(document: dict[str, Any], folder: str | Path) -> Path:
    """Write ``paper.json``, ``excitation_power.png``, ``sbr_phantom.png``, ``edge_drop.png`` and
    ``report.html``/``.md``; returns the HTML's path."""
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
    _sbr_figure(document["sbr_gain"], folder / "sbr_phantom.png")
    _sbr_section(report, document["sbr_gain"])
    _field_figure(document["magnification"], document["edge_drop"], folder / "edge_drop.png")
    _field_section(report, document["magnification"], document["edge_drop"])
    return report.write(folder)
