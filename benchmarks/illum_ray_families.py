"""Where each collimator loses its light: every LED ray sorted by the first surface of the part
it meets (lens, cavity wall → TIR wall, flat entry ring, outer wall, none) and by where it ends
(delivered into the circle, outside it, LED board — mostly light the excitation filter reflects
back —, housing), with the angle from the unit's axis of the rays that passed the filter.

Traced with the authors' LED profile, spectrum and excitation coating table, four units, at one
placement for every part (default: the authors' part's re-aim, 45° / 10 mm / +2.5 mm).

    .venv/bin/python benchmarks/illum_ray_families.py                       # authors' STL + the paper's CAD part
    .venv/bin/python benchmarks/illum_ray_families.py --design out/design.yaml  # + a design's own part
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from cm2optics.design import load_preset
from cm2optics.illumination.compare import setup_from_options, stl_collimator
from cm2optics.illumination.geometry import Absorber, CollimatorMesh, build_scene, collimator_from_design
from cm2optics.illumination.metrics import figures_of_merit
from cm2optics.illumination.tracer import Status, emit_rays, trace

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT.parent / "shared" / "reference" / "cm2-v2"
AUTHORS_CAVITY_RADIUS_MM = 0.7275
"""Cavity radius of the authors' part, measured from its STL (``compare_with_reference``)."""
FAMILIES = ("lens", "cavity wall (TIR)", "entry ring", "outer wall", "missed")


def reference_inputs(design):
    """(setup, authors' part): the tracer's inputs from the authors' LED profile, spectrum and
    coating table, and their collimator STL with the LED at its cavity mouth."""
    setup = setup_from_options(
        design,
        led_profile=REFERENCE / "led_angular_profile.csv",
        led_spectrum=REFERENCE / "led_spectrum.csv",
        filter_table=REFERENCE / "coating_real_ex.csv",
    )
    authors = stl_collimator(design, REFERENCE / "CM2_V2_freeform_illuminator.stl", [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])
    return setup, authors


def first_surfaces(collimator: CollimatorMesh, origin: np.ndarray, direction: np.ndarray, cavity_radius_mm: float):
    """The family of each ray (LED frame, mm): the first face of the part it meets."""
    mesh = collimator.mesh
    hits, ray, triangle = mesh.ray.intersects_location(origin, direction, multiple_hits=False)
    family = np.full(len(origin), "missed", dtype=object)
    r, z = np.hypot(hits[:, 0], hits[:, 1]), hits[:, 2]
    bottom = mesh.bounds[0, 2] + 1e-3
    inside = r < cavity_radius_mm - 0.02
    on_cavity_wall = np.abs(r - cavity_radius_mm) <= 0.02
    family[ray] = np.where(
        z < bottom, "entry ring", np.where(inside, "lens", np.where(on_cavity_wall, "cavity wall (TIR)", "outer wall"))
    )
    return family


def ray_families(design, collimator: CollimatorMesh, cavity_radius_mm: float, setup, rays: int, seed: int) -> dict:
    scene = build_scene(design, collimator)
    record = trace(scene, setup.source, rays, transmission=setup.transmission, seed=seed)
    figures = figures_of_merit(record, scene)
    batch = emit_rays(scene, setup.source, rays, seed)  # the same rays, in the same order
    family = np.empty(record.rays, dtype=object)
    for unit, pose in enumerate(scene.poses):
        pick = record.unit == unit
        inverse = np.linalg.inv(pose)
        origin = batch.origin_mm[pick] @ inverse[:3, :3].T + inverse[:3, 3]
        family[pick] = first_surfaces(collimator, origin, batch.direction[pick] @ inverse[:3, :3].T, cavity_radius_mm)
    radius = np.hypot(record.hit_mm[:, 0], record.hit_mm[:, 1])
    on_sample = record.status == int(Status.SAMPLE)
    inside = on_sample & (radius <= scene.field_radius_mm)
    fates = {
        "delivered": inside,
        "outside the circle": (on_sample & ~inside) | (record.status == int(Status.ESCAPED)),
        "LED board": record.status == int(Status.ABSORBED) + int(Absorber.LED_BOARD),
        "housing": record.status == int(Status.ABSORBED) + int(Absorber.HOUSING),
    }
    axis = scene.unit_axes[record.unit]
    cos_axis = np.einsum("ij,ij->i", np.nan_to_num(record.exit_direction), axis)
    angle = np.degrees(np.arccos(np.clip(cos_axis, -1.0, 1.0)))
    rows = {}
    for name in FAMILIES:
        pick = family == name
        if not pick.any():
            continue
        passed = pick & record.passed
        rows[name] = {
            "share": round(float(pick.mean()), 4),
            **{fate: round(float((pick & mask).mean()), 4) for fate, mask in fates.items()},
            "passed_filter": round(float(passed.mean()), 4),
            "angle_after_filter_deg_p50_p90": (
                [round(float(v), 1) for v in np.percentile(angle[passed], [50, 90])] if passed.any() else None
            ),
        }
    return {
        "part": collimator.label,
        "delivered_fraction": round(figures.delivered_fraction.value, 4),
        "uniformity_cv": round(figures.uniformity_cv.value, 4),
        "uniformity_cv_noise": round(figures.uniformity_cv_noise, 4),
        "throughput": round(figures.throughput.value, 4),
        "families": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--design", action="append", default=[], help="design YAML whose own part to add (repeatable)")
    parser.add_argument("--placement", default="45,10,2.5", help="tilt (deg), offset (mm), aim (mm) of every unit")
    parser.add_argument("--rays", type=int, default=400_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file for the table")
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import PAPER_COLLIMATOR  # the paper's collimating CAD part (the tests' fixture)

    tilt, offset, aim = map(float, args.placement.split(","))
    placement = {
        "led_array.tilt_deg": tilt,
        "led_array.offset_mm": offset,
        "led_array.aim_mm": aim,
        "led_array.azimuth_deg": 0.0,
    }
    paper = load_preset("cm2-v2").with_changes({**PAPER_COLLIMATOR, **placement})
    setup, authors = reference_inputs(paper)
    parts = [
        (paper, authors, AUTHORS_CAVITY_RADIUS_MM),
        (
            paper,
            dataclasses.replace(collimator_from_design(paper), label="paper collimating part (CAD)"),
            paper.collimator.cavity_radius_mm,
        ),
    ]
    for path in args.design:
        design = load_preset(path).with_changes(placement)
        part = dataclasses.replace(collimator_from_design(design), label=f"{Path(path).stem} (CAD)")
        parts.append((design, part, design.collimator.cavity_radius_mm))
    table = [ray_families(d, c, a, setup, args.rays, args.seed) for d, c, a in parts]
    print(json.dumps(table, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
