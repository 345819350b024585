"""Re-aim a fixed collimator: trace it at every placement of a grid (tilt, aim point, offset)
whose units clear the imaging tower, with the authors' LED profile, spectrum and excitation
coating table, and retrace the brightest placement with CV ≤ --max-cv at --final-rays.

The comparison row of issue 16: the authors' printed part (reference STL, LED at its cavity
mouth) re-aimed, against a design found by ``cm2 illum optimize --free-aim``.

    .venv/bin/python benchmarks/illum_reaim.py                        # the authors' STL
    .venv/bin/python benchmarks/illum_reaim.py --design out/design.yaml  # a design's own part
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
from cm2optics.illumination.compare import setup_from_options, stl_collimator
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.metrics import figures_of_merit
from cm2optics.illumination.tracer import trace
from cm2optics.optics.layout import unit_clashes

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "cm2-v2"


def _figures(design, collimator, setup, rays: int, seed: int) -> dict:
    scene = build_scene(design, collimator)
    f = figures_of_merit(trace(scene, setup.source, rays, transmission=setup.transmission, seed=seed), scene)
    cv_true = math.sqrt(max(f.uniformity_cv.value**2 - f.uniformity_cv_noise**2, 0.0))
    return {
        "delivered_fraction": round(f.delivered_fraction.value, 4),
        "delivered_fraction_stderr": round(f.delivered_fraction.stderr, 4),
        "uniformity_cv": round(f.uniformity_cv.value, 4),
        "uniformity_cv_stderr": round(f.uniformity_cv.stderr, 4),
        "uniformity_cv_noise": round(f.uniformity_cv_noise, 4),
        "uniformity_cv_corrected": round(cv_true, 4),
        "rays": rays,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--design", default="cm2-v2", help="preset or design YAML (its own part unless --stl)")
    parser.add_argument("--stl", default=None, help="collimator STL (default: the authors' part, if no --design)")
    parser.add_argument("--tilts", default="40,45,50,55")
    parser.add_argument("--aims", default="0,1,2")
    parser.add_argument("--offsets", default="6.7,8")
    parser.add_argument("--rays", type=int, default=200_000)
    parser.add_argument("--final-rays", type=int, default=1_000_000)
    parser.add_argument("--max-cv", type=float, default=0.10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file for the table")
    args = parser.parse_args()

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
    grid = itertools.product(*(map(float, a.split(",")) for a in (args.tilts, args.aims, args.offsets)))
    rows = []
    start = time.perf_counter()
    for tilt, aim, offset in grid:
        changes = {"led_array.tilt_deg": tilt, "led_array.aim_mm": aim, "led_array.offset_mm": offset}
        placed = design.with_changes(changes)
        clashes = unit_clashes(placed)
        row = {"placement": changes, **({"skipped": clashes[0]} if clashes else {})}
        if not clashes:
            row.update(_figures(placed, collimator, setup, args.rays, args.seed))
        rows.append(row)
        print(json.dumps(row), flush=True)
    uniform = [r for r in rows if "skipped" not in r and r["uniformity_cv_corrected"] <= args.max_cv]
    best = max(uniform or [r for r in rows if "skipped" not in r], key=lambda r: r["delivered_fraction"])
    final = _figures(design.with_changes(best["placement"]), collimator, setup, args.final_rays, args.seed + 1)
    result = {
        "collimator": collimator.label,
        "placement": best["placement"],
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
