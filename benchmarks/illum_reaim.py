"""Re-aim a fixed collimator: trace it at every placement of a grid (tilt, aim point, offset)
whose units clear the imaging tower, with the authors' LED profile, spectrum and excitation
coating table, and retrace the brightest placement with CV ≤ --max-cv at --final-rays.

Each placement's SBR is computed from its traced beam (``illumination.traced_sbr``, per photon the
LEDs emit: the fluorescence excited where rays land in the field against the glow and the specular
reflection of all that land; interference-only and hybrid chains) beside the emission model's (its
model beams at the same placement); ``--min-sbr-interference`` and
``--min-sbr-hybrid`` keep only placements whose traced SBR reaches them, so a brighter aim does
not buy its light with excitation mirrored into the lenslets.

The comparison row of issue 16: the authors' printed part (reference STL, LED at its cavity
mouth) re-aimed, against a design found by ``cm2 illum optimize --free-aim``.

    .venv/bin/python benchmarks/illum_reaim.py                        # the authors' STL
    .venv/bin/python benchmarks/illum_reaim.py --design out/design.yaml  # a design's own part
    .venv/bin/python benchmarks/illum_reaim.py --design X.yaml --min-sbr-hybrid 4000  # SBR-aware
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import time
from pathlib import Path

from cm2optics.design import load_preset
from cm2optics.emission.sbr import signal_and_background
from cm2optics.formats.outputs import OutputError, check_output
from cm2optics.illumination.compare import setup_from_options, stl_collimator
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.metrics import figures_of_merit
from cm2optics.illumination.traced_sbr import COARSE_SAMPLING, traced_sbr
from cm2optics.illumination.tracer import trace
from cm2optics.optics.layout import unit_clashes

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "cm2-v2"


def _figures(design, collimator, setup, rays: int, seed: int) -> dict:
    scene = build_scene(design, collimator)
    record = trace(scene, setup.source, rays, transmission=setup.transmission, seed=seed)
    f = figures_of_merit(record, scene)
    cv_true = math.sqrt(max(f.uniformity_cv.value**2 - f.uniformity_cv_noise**2, 0.0))
    sbr = traced_sbr(record, scene, seed=seed, **COARSE_SAMPLING)
    model = signal_and_background(design, beam_samples=8, **COARSE_SAMPLING)
    return {
        "delivered_fraction": round(f.delivered_fraction.value, 4),
        "delivered_fraction_stderr": round(f.delivered_fraction.stderr, 4),
        "uniformity_cv": round(f.uniformity_cv.value, 4),
        "uniformity_cv_stderr": round(f.uniformity_cv.stderr, 4),
        "uniformity_cv_noise": round(f.uniformity_cv_noise, 4),
        "uniformity_cv_corrected": round(cv_true, 4),
        "sbr_interference_only": round(sbr.sbr_interference_only, 3),
        "sbr_hybrid": round(sbr.sbr_hybrid, 1),
        "sbr_model_interference_only": round(model.sbr_interference_only, 3),
        "sbr_model_hybrid": round(model.sbr_hybrid, 1),
        "rays": rays,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--design", default="cm2-v2", help="preset or design YAML (its own part unless --stl)")
    parser.add_argument("--stl", default=None, help="collimator STL (default: the authors' part, if no --design)")
    parser.add_argument("--tilts", default="40,45,50,55")
    parser.add_argument("--aims", default="0,1,2")
    parser.add_argument("--offsets", default="6.7,8")
    parser.add_argument("--azimuths", default=None, help="unit azimuths, deg (default: the design's)")
    parser.add_argument("--rays", type=int, default=200_000)
    parser.add_argument("--final-rays", type=int, default=1_000_000)
    parser.add_argument("--max-cv", type=float, default=0.10)
    parser.add_argument("--min-sbr-interference", type=float, default=0.0, help="traced SBR, interference only")
    parser.add_argument("--min-sbr-hybrid", type=float, default=0.0, help="traced SBR, with the film")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file for the table")
    args = parser.parse_args()
    if args.out:  # never over one of its own inputs (an existing table is replaced)
        try:
            check_output(args.out, command="illum_reaim", inputs=(args.design, args.stl), overwrite=True)
        except OutputError as error:
            parser.error(str(error))

    design = load_preset(args.design)
    if args.stl or args.design == "cm2-v2":
        path = Path(args.stl) if args.stl else REFERENCE / "CM2_V2_freeform_illuminator.stl"
        collimator = stl_collimator(design, path, [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])  # the authors' LED: cavity mouth
    else:
        collimator = collimator_from_design(design)
    setup = setup_from_options(
        design,
        led_profile=REFERENCE / "led_angular_profile.csv",
        led_spectrum=REFERENCE / "led_spectrum.csv",
        filter_table=REFERENCE / "coating_real_ex.csv",
    )
    azimuths = args.azimuths or str(design.led_array.azimuth_deg)
    axes = (args.tilts, args.aims, args.offsets, azimuths)
    grid = itertools.product(*(map(float, a.split(",")) for a in axes))
    rows = []
    start = time.perf_counter()
    for tilt, aim, offset, azimuth in grid:
        changes = {
            "led_array.tilt_deg": tilt,
            "led_array.aim_mm": aim,
            "led_array.offset_mm": offset,
            "led_array.azimuth_deg": azimuth,
        }
        placed = design.with_changes(changes)
        clashes = unit_clashes(placed)
        row = {"placement": changes, **({"skipped": clashes[0]} if clashes else {})}
        if not clashes:
            row.update(_figures(placed, collimator, setup, args.rays, args.seed))
        rows.append(row)
        print(json.dumps(row), flush=True)
    uniform = [
        r
        for r in rows
        if "skipped" not in r
        and r["uniformity_cv_corrected"] <= args.max_cv
        and r["sbr_interference_only"] >= args.min_sbr_interference
        and r["sbr_hybrid"] >= args.min_sbr_hybrid
    ]
    best = max(uniform or [r for r in rows if "skipped" not in r], key=lambda r: r["delivered_fraction"])
    final = _figures(design.with_changes(best["placement"]), collimator, setup, args.final_rays, args.seed + 1)
    result = {
        "collimator": collimator.label,
        "placement": best["placement"],
        "constraints_met": bool(uniform),
        "final": final,
        "grid": rows,
        "seconds": round(time.perf_counter() - start, 1),
        "load": os.getloadavg()[0],
    }
    print(json.dumps({k: v for k, v in result.items() if k != "grid"}, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
