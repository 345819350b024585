"""The illumination section of the ``cm2 demo`` report (demo size: a few hundred thousand rays)."""

from __future__ import annotations

import time
from pathlib import Path

from cm2optics.design import SystemDesign
from cm2optics.optics import first_order
from cm2optics.reports.document import Report

__all__ = ["DEMO_RAYS", "REFERENCE_DIR", "add_illumination_section"]

#: Rays per design in the demo (all LEDs together).
DEMO_RAYS = 400_000
#: The original device's reference data in a developer checkout (absent on a user's machine).
REFERENCE_DIR = Path(__file__).resolve().parents[3] / "shared" / "reference" / "cm2-v2"


def _pct(estimate) -> str:
    return f"{100 * estimate.value:.1f} ± {100 * estimate.stderr:.2f} %"


def _placement(design: SystemDesign) -> str:
    """The units' placement in words: tilt, offset, aim point and azimuth (rounded)."""
    led = design.led_array
    side = "short of" if led.aim_mm > 0 else "past"
    aim = f", aimed {abs(led.aim_mm):.2f} mm {side} the field centre" if led.aim_mm else ""
    return (
        f"{led.tilt_deg:.1f}° tilt, {led.offset_mm:.2f} mm off-axis{aim}, first unit at {led.azimuth_deg:.1f}° azimuth"
    )


def _figure_rows(design: SystemDesign, results: list) -> list[list[str]]:
    """The comparison table's rows: one figure of merit a row, one design a column."""
    rows = [
        ["throughput", *[_pct(r.throughput) for r in results]],
        [f"delivered fraction (Ø{design.volume.field_mm:g} mm)", *[_pct(r.delivered_fraction) for r in results]],
        [
            f"power (mW, {design.led_array.count} × {results[0].led_flux_mw:g} mW LEDs)",
            *[f"{r.power_mw.value:.0f} ± {r.power_mw.stderr:.1f}" for r in results],
        ],
        [
            "uniformity CV (MC noise floor)",
            *[f"{_pct(r.uniformity_cv)} ({100 * r.uniformity_cv_noise:.1f} %)" for r in results],
        ],
        ["uniformity min/max", *[f"{r.uniformity_min_max.value:.2f}" for r in results]],
        ["passing within 30° of the axis", *[_pct(r.fraction_within_30deg) for r in results]],
        [
            "beam half-angle 50 % / 90 % (°)",
            *[f"{r.beam_half_angle_50_deg.value:.1f} / {r.beam_half_angle_90_deg.value:.1f}" for r in results],
        ],
    ]
    return rows


def _add_bounds(report: Report, design: SystemDesign, setup) -> tuple[dict, dict]:
    """Add the étendue and uniform-beam bounds to ``report``, their spectral ceiling from the
    trace's own filter and LED spectrum (``setup``); returns both bounds."""
    from cm2optics.illumination.bounds import etendue_bound, uniform_beam_bound

    spectrum = setup.source.spectrum
    bound = etendue_bound(design, setup.transmission, spectrum=spectrum)
    report.paragraph(
        f"Étendue: a 1-mm² Lambertian emitter has G = {bound['g_source_mm2sr']:.2f} mm²·sr; one unit's clear aperture and the "
        f"field circle span G = {bound['g_target_mm2sr']:.2f} mm²·sr, so étendue allows {100 * bound['geometric_bound']:.0f} % "
        f"onto the circle; the filter passes at most {100 * bound['spectral_ceiling']:.1f} % of the LED's spectrum (all rays at "
        f"normal incidence): the delivered fraction cannot exceed {100 * bound['delivered_bound']:.1f} %."
    )
    uniform = uniform_beam_bound(design, transmission=setup.transmission, spectrum=spectrum)
    report.paragraph(
        f"Uniformity: the best rotationally symmetric beam aimed along each unit's axis (any revolved collimator, ideal "
        f"point-like source) puts at most {100 * uniform['output_bound']:.1f} % of a unit's output inside the circle with "
        f"the array's CV ≤ {100 * uniform['max_cv']:.0f} %, i.e. ≤ {100 * uniform['delivered_bound']:.1f} % of the LED's power "
        "after the filter (linear programme over the beam's radial profile, `cm2optics.illumination.bounds`)."
    )
    return bound, uniform


def add_illumination_section(
    report: Report, design: SystemDesign, out_dir: str | Path, rays: int = DEMO_RAYS, heading: str = "Illumination"
) -> dict:
    """Trace V1, the design's collimator and (when the reference data is present) the authors'
    printed part; add the comparison, the energy ledgers and the irradiance maps to ``report``.

    out_dir: the report's folder; maps go to ``out_dir/illumination/``. rays: rays per design.
    Returns the figures as JSON-able data (``illumination/illumination.json`` too).
    """
    from cm2optics.formats.atomic import write_json_atomic
    from cm2optics.illumination.compare import compare_designs, configurations, setup_from_options, stl_collimator
    from cm2optics.illumination.metrics import DEFINITIONS, write_maps_png
    from cm2optics.optics.backend import mitsuba, variant

    folder = Path(out_dir) / "illumination"
    mitsuba()
    start = time.perf_counter()
    stl = None
    reference = REFERENCE_DIR / "CM2_V2_freeform_illuminator.stl"
    if reference.is_file():
        stl = stl_collimator(design, reference, [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])
        stl = type(stl)("authors' part (reference STL)", stl.mesh, stl.material)
    setup = setup_from_options(design, rays=rays)
    results = compare_designs(design, setup, configurations(design, stl))
    elapsed = time.perf_counter() - start

    report.heading(heading)
    report.paragraph(
        f"Ray trace of LED → collimator → excitation filter → sample plane on Mitsuba 3 ({variant().variant}), "
        f"{rays:,} rays per design over the {design.led_array.count} LEDs ({_placement(design)}), housings absorbing, "
        f"sample plane at z = {first_order.object_plane_z_mm(design):.2f} mm; "
        f"{elapsed:.1f} s in all. LED: {setup.notes['led_profile']}; spectrum: {setup.notes['led_spectrum']}. "
        f"Filter: {setup.notes['excitation_filter']}. Each figure ± its Monte Carlo standard error."
    )
    rows = _figure_rows(design, results)
    report.table(["figure", *[r.label for r in results]], rows)
    ledger_keys = [k for k in results[0].ledger if k not in ("closure", "unaccounted")]
    report.paragraph("Energy ledger (fractions of the emitted power; delivered + absorbed + escaped = 1):")
    report.table(
        ["entry", *[r.label for r in results]],
        [[k, *[f"{r.ledger[k].value:.4f}" for r in results]] for k in ledger_keys],
    )
    bound, uniform = _add_bounds(report, design, setup)
    report.paragraph("Definitions: " + " ".join(f"{k}: {v}." for k, v in DEFINITIONS.items()))
    data = {
        "rays": rays,
        "backend": variant().variant,
        "designs": {r.label: r.summary() for r in results},
        "etendue_bound": bound,
        "uniform_beam_bound": uniform,
    }
    for r in results:
        name = "".join(c if c.isalnum() else "_" for c in r.label).strip("_").lower()
        write_maps_png(r, folder / f"irradiance_{name}.png")
        report.figure(
            f"illumination/irradiance_{name}.png", f"Irradiance on the sample plane: {r.label} (one LED, and the array)"
        )
    write_json_atomic(folder / "illumination.json", data)
    return data
