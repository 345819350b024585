"""A Sobol sweep of the TIR wall's cos 2φ term with the wall's spread, the lens's angle and the placement
free, from the enclosed-die part (issue 16, session 13; BENCHMARKS.md "A TIR wall that departs from
revolution").

The term is swept as ``u``, a signed fraction of the largest |tir_cos2| whose wall still fits the
square footprint (0.005 mm kept from the flange's sides) for the candidate's own profile, so that the
sweep does not spend its traces on walls that cannot be built; the height is the lowest ≥ 2.04 mm that
keeps the wall below the flange. Every candidate is traced with the authors' LED profile, spectrum and
excitation coating table (``optimize.evaluate_candidate``, 2 × 10⁵ rays, seed 1, one thread) and
appended to a JSON-lines file, so an interrupted run resumes where it stopped.

    .venv/bin/python benchmarks/illum_tir_azimuthal.py --out sweep.jsonl --samples 40 --sobol-seed 0 \\
        --box '{"u": [-1, -0.4], "collimator.tir_spread_deg": [32.5, 37], ...}'

``--probe '[{"collimator.tir_cos2": -0.05}, ...]'`` instead traces the given design changes one by one: the beam
reaching the filter (traced without it, 10⁵ rays) and its RMS widths across and in the units' plane of tilt, then
the delivered fraction and noise-corrected CV′ with it (2 × 10⁵ rays), all on the sweep's swept mesh.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from illum_ray_families import REFERENCE
from scipy.stats import qmc

from cm2optics.design import DesignError, load_preset
from cm2optics.illumination.optimize import evaluate_candidate
from cm2optics.optics.collimator import profile_from_parameters, tir_wall_reach_mm

ROOT = Path(__file__).resolve().parents[1]
BASE = str(ROOT / "benchmarks/designs/cm2-v2-enclosed-spread.yaml")
INPUTS = tuple(str(REFERENCE / name) for name in ("led_angular_profile.csv", "led_spectrum.csv", "coating_real_ex.csv"))
#: Kept between the wall's farthest reach and the flange's sides, mm.
MARGIN_MM = 0.005


def resolve(base, values: dict[str, float]) -> dict[str, float]:
    """The design changes of a sweep point: ``u`` (a signed fraction of the largest |tir_cos2| the
    footprint allows) turned into ``collimator.tir_cos2``, and the lowest height ≥ 2.04 mm that
    holds the wall below the flange (the filter kept on the exit face)."""
    values = dict(values)
    u = values.pop("u")
    fields = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith("collimator.")}
    collimator = dataclasses.replace(base.collimator, height_mm=6.0, **fields)
    profile = profile_from_parameters(collimator, base.led.peak_nm)
    height = max(2.04, round(float(profile.tir_z_mm[-1]) + collimator.flange_mm + 0.002, 3))
    entry, end, half = profile.outer_radius_entry_mm, float(profile.tir_r_mm[-1]), collimator.footprint_mm / 2
    low, high = 0.0, 0.5
    for _ in range(40):  # bisect the largest |c₂| whose wall fits
        mid = (low + high) / 2
        low, high = (mid, high) if tir_wall_reach_mm(entry, end, mid, 0.0) < half - MARGIN_MM else (low, mid)
    values["collimator.tir_cos2"] = round(u * low, 5)
    values["collimator.height_mm"] = height
    values["led_array.excitation_gap_mm"] = height + collimator.led_gap_mm
    return values


def probe(base, values: dict[str, float], rays: int, seed: int) -> dict[str, float]:
    """The beam of the design changes ``values`` traced without the filter (``rays`` // 2 rays): the share
    reaching the filter's plane and the RMS widths of its directions in each unit's frame (degrees,
    atan of the tangent-plane RMS; x across the plane of tilt, y in it); then the delivered fraction and
    CV′ with the filter (``rays``)."""
    import math

    from illum_ray_families import reference_inputs

    from cm2optics.illumination.geometry import build_scene
    from cm2optics.illumination.optimize import candidate_collimator
    from cm2optics.illumination.tracer import trace
    from cm2optics.optics.layout import led_poses

    setup, _ = reference_inputs(base)
    design, collimator, _ = candidate_collimator(base, values)
    record = trace(build_scene(design, collimator, excitation_filter=False), setup.source, rays // 2, seed=seed)
    out = record.passed
    rotation = np.stack([pose.matrix[:3, :3] for pose in led_poses(design)])
    local = np.einsum("ni,nij->nj", record.exit_direction[out], rotation[record.unit[out]])
    rms = (local[:, :2] / local[:, 2:]).std(axis=0)
    entry = evaluate_candidate(base.to_dict(), values, rays, seed, 0.10, threads=1, inputs=INPUTS)
    return {
        "reaches_filter": round(float(out.mean()), 4),
        "rms_x_deg": round(math.degrees(math.atan(rms[0])), 2),
        "rms_y_deg": round(math.degrees(math.atan(rms[1])), 2),
        **{k: entry.get(k) for k in ("delivered_fraction", "uniformity_cv_corrected", "throughput", "reason")},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--box", help="JSON {name: [low, high]}: 'u' and design fields")
    parser.add_argument("--probe", help="JSON list of design changes to trace one by one (no sweep)")
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--sobol-seed", type=int, default=0)
    parser.add_argument("--rays", type=int, default=200_000)
    parser.add_argument("--seed", type=int, default=1, help="trace seed")
    parser.add_argument("--out", help="JSON-lines file (appended; resumes)")
    args = parser.parse_args()
    base = load_preset(BASE)
    if args.probe:
        from cm2optics.optics.backend import mitsuba

        mitsuba()
        import drjit as dr

        dr.set_thread_count(1)
        for values in json.loads(args.probe):
            print(json.dumps({"changes": values, **probe(base, values, args.rays, args.seed)}), flush=True)
        return
    if not (args.box and args.out):
        parser.error("a sweep needs --box and --out")
    box = json.loads(args.box)
    if "u" not in box:
        parser.error("--box must sweep 'u' (the cos 2φ term as a fraction of its largest buildable value)")
    out = Path(args.out)
    done = (
        {json.loads(line)["index"] for line in out.read_text().splitlines() if line.strip()} if out.exists() else set()
    )
    names = list(box)
    low, high = np.array([box[k][0] for k in names]), np.array([box[k][1] for k in names])
    points = qmc.scale(qmc.Sobol(len(names), scramble=True, seed=args.sobol_seed).random(args.samples), low, high)
    data = base.to_dict()
    for i, point in enumerate(points):
        if i in done:
            continue
        start = time.time()
        raw = dict(zip(names, map(float, point), strict=True))
        try:
            values = resolve(base, raw)
        except (DesignError, ValueError, RuntimeError) as error:
            entry = {"parameters": raw, "feasible": False, "reason": str(error)[:200]}
        else:
            entry = evaluate_candidate(data, values, args.rays, args.seed, 0.10, threads=1, inputs=INPUTS)
        entry.update(index=i, wall_s=round(time.time() - start, 1))
        with out.open("a") as handle:
            handle.write(json.dumps(entry) + "\n")
        print(
            i, entry.get("feasible"), entry.get("delivered_fraction"), entry.get("uniformity_cv_corrected"), flush=True
        )


if __name__ == "__main__":
    main()
