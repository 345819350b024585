"""Benchmark: the Mitsuba/Dr.Jit illumination tracer against the plain NumPy reference tracer.

Both trace the same scene — four LED units with the design's collimator (CAD part), the
excitation filter, housings, the imaging tower and the sample plane — from the same rays,
with the same physics and random decisions, in the same run. The project's figure is the
whole pipeline for ``--rays`` LED rays: sampling, tracing and binning the irradiance on the
sample plane (after a first, compiling run); the reference traces ``--reference-rays`` of
them (brute-force intersections: it is too slow for more). Printed: rays/s of each, their
ratio, and the delivered fraction each found (they must agree).

    .venv/bin/python benchmarks/bench_illumination.py            # cm2-v2 CAD collimator
    .venv/bin/python benchmarks/bench_illumination.py --scene authors   # the authors' STL
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from pathlib import Path

import numpy as np

from cm2optics.design import load_preset
from cm2optics.illumination.excitation import design_filter_transmission
from cm2optics.illumination.geometry import build_scene, collimator_from_design, collimator_from_stl
from cm2optics.illumination.metrics import figures_of_merit
from cm2optics.illumination.reference_numpy import trace_rays_numpy
from cm2optics.illumination.scene import mitsuba_scene
from cm2optics.illumination.source import led_source
from cm2optics.illumination.tracer import Status, emit_rays, filter_table, trace, trace_rays
from cm2optics.optics.backend import mitsuba, variant

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "cm2-v2"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=1_000_000, help="rays traced by the project's tracer")
    parser.add_argument("--reference-rays", type=int, default=2_000, help="rays traced by the NumPy reference")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs of the project's tracer (best is kept)")
    parser.add_argument("--scene", choices=["design", "authors"], default="design")
    args = parser.parse_args()

    design = load_preset("cm2-v2")
    mitsuba()
    if args.scene == "authors":
        stl = REFERENCE / "CM2_V2_freeform_illuminator.stl"
        if not stl.is_file():
            raise SystemExit(f"the authors' STL is not at {stl}")
        collimator = collimator_from_stl(stl, [0, 0, 1], [0, 0, -1], design.collimator.material, "authors' part")
    else:
        collimator = collimator_from_design(design)
    scene = build_scene(design, collimator)
    source = led_source(design)
    transmission = design_filter_transmission(design)
    msc = mitsuba_scene(scene)
    triangles = sum(len(p.faces) for p in scene.parts)

    # The project's pipeline: sample → trace → bin (figures of merit include the binning).
    trace(scene, source, args.rays, transmission=transmission, seed=99, msc=msc)  # compile
    best = math.inf
    for k in range(args.repeat):
        start = time.perf_counter()
        record = trace(scene, source, args.rays, transmission=transmission, seed=k, msc=msc)
        figures = figures_of_merit(record, scene)
        best = min(best, time.perf_counter() - start)
    ours_rate = args.rays / best

    # The reference on a subset of the same kind of rays, and the project's tracer on exactly those.
    batch = emit_rays(scene, source, args.reference_rays, seed=7)
    table = filter_table(scene, source, transmission)
    start = time.perf_counter()
    reference = trace_rays_numpy(scene, batch, table, seed=7)
    reference_seconds = time.perf_counter() - start
    reference_rate = len(batch.unit) / reference_seconds
    same = trace_rays(scene, batch, table, seed=7, msc=msc)
    agree = float(np.mean(same.status == reference.status))
    delivered_ref = float(
        np.mean((reference.status == Status.SAMPLE) & (np.hypot(*reference.hit_mm.T) <= scene.field_radius_mm))
    )

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; Mitsuba variant {variant().variant}"
    )
    print(f"scene: {scene.label}, {scene.units} LED units, {triangles:,} triangles")
    print(
        f"project (Mitsuba/Dr.Jit): {args.rays:,} rays sampled, traced and binned in {best:.2f} s "
        f"→ {ours_rate / 1e6:.2f} M rays/s (best of {args.repeat}); delivered {figures.delivered_fraction.value:.4f}"
    )
    print(
        f"reference (NumPy, brute force): {len(batch.unit):,} rays in {reference_seconds:.2f} s "
        f"→ {reference_rate:,.0f} rays/s; delivered {delivered_ref:.4f} ± {math.sqrt(delivered_ref * (1 - delivered_ref) / len(batch.unit)):.4f}"
    )
    print(f"same rays, same fate in both tracers: {agree:.1%}")
    print(f"ratio: {ours_rate / reference_rate:,.0f}× faster")


if __name__ == "__main__":
    main()
