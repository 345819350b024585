"""``cm2 demo``: every stage built so far, at demo size, into one report with figures.

Stages so far: the design's first-order optics; the printable parts (CAD export with checks
and pictures), with the collimator compared to the original authors' part when the reference
data is present beside the repository; the spectra, filters and the hybrid filter's SBR; the illumination traced through the
collimators and excitation filters onto the sample; a traced PSF calibration scan; the 3D-LSV
forward model built from that scan (effective-PSF basis), checked against traced points between
its nodes; a synthetic volume simulated through that model, reconstructed with the model-based
baselines and evaluated; CM²Net with the shipped weights beside FISTA on a measurement simulated
at the weights' own geometry; the calibration loop finding an effect injected into a traced scan
without telling it. One chain: design → traced scan → model → data → volume.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rich.console import Console

from cm2optics.design import SystemDesign
from cm2optics.reports.calibration_demo import add_calibration_section
from cm2optics.reports.document import Report
from cm2optics.reports.emission import CHAIN_SCAN, add_psf_section
from cm2optics.reports.illumination import add_illumination_section
from cm2optics.reports.lsv import add_lsv_section
from cm2optics.reports.recon import add_baseline_section, add_net_section
from cm2optics.reports.spectra import add_spectra_section

#: Where the original device's reference data sits in a developer checkout (absent for users).
REFERENCE_DIR = Path(__file__).resolve().parents[3] / "shared" / "reference" / "cm2-v2"


def _design_section(report: Report, design: SystemDesign) -> None:
    from cm2optics.reports.design import design_summary

    report.heading("1. Design: first-order optics")
    report.paragraph(
        "Paraxial imaging through one lenslet (emission filter, PMMA lenslet, absorption film) at "
        f"{design.imaging.design_wavelength_nm:g} nm. Heights in the device frame: z = 0 on the sensor, +z towards the sample."
    )
    report.table(["quantity", "value"], [[k, v] for k, v in design_summary(design).items()])


def _cad_section(report: Report, design: SystemDesign, out_dir: Path) -> None:
    from cm2optics.cad.export import export_design, size_text

    start = time.perf_counter()
    manifest = export_design(design, out_dir / "cad", wall_samples=5000)
    elapsed = time.perf_counter() - start
    report.heading("2. Printable parts")
    report.paragraph(
        f"{len(manifest['parts'])} parts exported as STL and STEP in {elapsed:.1f} s (tolerance {manifest['tolerance_um']} µm). "
        f"Checks: {', '.join(f'{k} = {v}' for k, v in manifest['checks'].items())}."
    )
    rows = []
    for part in manifest["parts"]:
        rows.append(
            [
                part["name"],
                part["count"],
                "printed" if part["printed"] else "bought/cut",
                f"{part['volume_mm3']:.3f}",
                f"{part['volume_error'] * 100:.3f} %",
                size_text(part["bbox_mm"]),
                part["watertight"],
                f"{part['min_wall_mm']:.3f}",
            ]
        )
    report.table(["part", "n", "kind", "volume mm³", "mesh vol. error", "size mm", "watertight", "min wall mm"], rows)
    report.table(
        ["seated part", "seat", "clearance mm"],
        [[f["part"], f["seat"], f["clearance_mm"]] for f in manifest["assembly"]["fits"]],
    )
    clashes = manifest["assembly"]["interferences"]
    report.paragraph(f"Interferences between placed parts: {'none' if not clashes else clashes}.")
    report.figure("cad/assembly.png", "The assembly in the device frame")
    report.figure("cad/assembly_section.png", "Section through the optical axis (y = 0)")
    for name in ("mla", "collimator", "mla_housing", "led_housing", "base_plate"):
        if any(p["name"] == name for p in manifest["parts"]):
            report.figure(f"cad/{name}.png", name)
    _collimator_comparison(report, design)


def _collimator_comparison(report: Report, design: SystemDesign) -> None:
    reference = REFERENCE_DIR / "CM2_V2_freeform_illuminator.stl"
    if design.collimator is None or not reference.is_file():
        return
    from cm2optics.cad.collimator import compare_with_reference

    comparison = compare_with_reference(design, reference)
    report.paragraph("The collimator beside the original authors' printed part (reference data, not shipped):")
    rows = [[quantity, values["ours"], values["reference"]] for quantity, values in comparison.items()]
    report.table(["quantity", "this design", "authors' part"], rows)


def _traced_in_model_units(design: SystemDesign) -> Callable[[tuple[float, float, float]], np.ndarray]:
    """position (mm) → the traced image of one :data:`CHAIN_SCAN` bead there, divided by the total of
    the in-focus bead on the axis (the 3D-LSV model's unit)."""
    from cm2optics.emission.image import render_emitters
    from cm2optics.emission.psf import PSFSettings
    from cm2optics.formats.emitters import Emitters

    settings = PSFSettings(binning=CHAIN_SCAN["binning"])

    def image(position: tuple[float, float, float]) -> np.ndarray:
        table = Emitters.from_positions_um(np.array([position]) * 1e3, np.array([CHAIN_SCAN["bead_um"]]), np.ones(1))
        return render_emitters(design, table, settings)

    unit = float(image((0.0, 0.0, 0.0)).sum())
    return lambda position: image(position) / unit


def run_demo(
    design: SystemDesign, out_dir: str | Path, *, analytic: bool = False, weights: str | Path | None = None
) -> Path:
    """Run the demo pipeline for ``design`` and return the path of the HTML report.

    The 3D-LSV model of sections 6–7 is built from section 5's traced calibration scan (one
    chain); ``analytic``: from a closed-form CM²-like scan instead (the fast fallback, about
    two minutes sooner). Section 8 uses the CM²Net weights ``weights`` (default: the shipped
    ones, :func:`~cm2optics.recon.net.weights.shipped_weights`); without them it says so. Section 9
    traces a 9-position scan with an MLA rotation it does not declare and runs the calibration
    loop on it (:func:`~cm2optics.reports.calibration_demo.add_calibration_section`)."""
    out_dir = Path(out_dir)
    console = Console(stderr=True)
    report = Report(f"cm2optics demo — {design.name}")
    timings: list[tuple[str, float]] = []

    def stage(number: int, label: str, run: Callable[[], object]) -> object:
        console.print(f"[bold]{number}/9[/] {label}")
        start = time.perf_counter()
        result = run()
        timings.append((f"{number}. {label}", time.perf_counter() - start))
        console.print(f"    {label}: {timings[-1][1]:.1f} s")
        return result

    stage(1, "design optics", lambda: _design_section(report, design))
    stage(2, "CAD export and checks", lambda: _cad_section(report, design, out_dir))
    stage(
        3,
        "spectra, filters and SBR",
        lambda: add_spectra_section(
            report, design, out_dir, title="3. Spectra, filters and the hybrid emission filter"
        ),
    )
    stage(4, "illumination", lambda: add_illumination_section(report, design, out_dir, heading="4. Illumination"))
    scan = stage(
        5,
        "PSFs and the calibration scan",
        lambda: add_psf_section(report, design, out_dir, title="5. PSFs and calibration scans"),
    )
    title = "6. The 3D-LSV forward model"
    if analytic:
        stage(
            6,
            "3D-LSV forward model (analytic fallback)",
            lambda: add_lsv_section(report, design, None, out_dir, title=title + " (analytic fallback)"),
        )
    else:
        stage(
            6,
            "3D-LSV forward model from the traced scan",
            lambda: add_lsv_section(
                report,
                design,
                scan,
                out_dir,
                rank=48,
                title=title,
                oversample=CHAIN_SCAN["oversample"],
                traced=_traced_in_model_units(design),
            ),
        )
    model = None if analytic else out_dir / "lsv" / "model.h5"
    stage(
        7,
        "synthetic volume, model-based reconstruction, metrics",
        lambda: add_baseline_section(report, design, model, out_dir, title="7. Synthetic data, baselines and metrics"),
    )
    stage(
        8,
        "CM²Net with the shipped weights beside FISTA",
        lambda: add_net_section(report, out_dir, weights=weights, title="8. CM²Net"),
    )
    stage(
        9,
        "calibration loop on a scan with an undeclared effect",
        lambda: add_calibration_section(
            report, design, out_dir, title="9. Calibration: an effect nobody declared, found"
        ),
    )
    report.heading("Run time")
    report.paragraph(f"Each section's wall time on this run ({sum(t for _, t in timings):.0f} s in all).")
    report.table(["section", "time s"], [[label, f"{seconds:.1f}"] for label, seconds in timings])
    return report.write(out_dir)
