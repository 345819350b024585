"""Where each collimator loses light inside its LED unit, with no excitation filter: every LED ray
sorted by the first face of the part it meets (lens, cavity wall → TIR wall, flat entry ring,
missed; ``illum_ray_families.first_surfaces``) and by where it ends:

* left the unit through the housing's aperture (its angle from the unit's axis at the exit);
* housing bore beside the part (below the part's top: light leaving through the part's side —
  TIR failures, the entry ring's rays);
* housing bore above the part (a beam too wide for the bore between the part and the lip);
* the lip's underside and edge (a beam too wide for the clear aperture);
* LED board (light sent back: Fresnel reflections at the entry, rays trapped and returned).

The bore's walls are split by thin absorbing tallies 1 µm inside them, so the tracer's ledger
tells the zones apart. Also traced bare (no housing): the fraction leaving the part forwards
(crossing a 20 × 20-mm plane above it), within 30° of the axis — the figures of issue 16's
independent trace of the authors' part (86–87 % forward, 74–75 % within 30°) — and back onto its
LED board without having left.

    .venv/bin/python benchmarks/illum_unit_losses.py --rays 400000   # authors' STL, cm2-v2, the cone wall
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from enum import IntEnum
from pathlib import Path

import numpy as np
from illum_ray_families import AUTHORS_CAVITY_RADIUS_MM, FAMILIES, first_surfaces, reference_inputs

from cm2optics.design import load_preset
from cm2optics.formats.outputs import OutputError, check_output
from cm2optics.illumination.geometry import (
    BOARD_Z_MM,
    Absorber,
    Part,
    Role,
    _place,
    _quads,
    _unit_layout,
    _walls,
    build_scene,
    collimator_from_design,
)
from cm2optics.illumination.tracer import Status, emit_rays, trace

ROOT = Path(__file__).resolve().parents[1]
TALLY_INSET_MM = 1e-3


class Zone(IntEnum):
    """Tally groups of the split housing (beyond :class:`Absorber`'s)."""

    BORE_BESIDE_PART = 16
    BORE_ABOVE_PART = 17


def zoned_scene(design, collimator):
    """``build_scene`` without the filter, with tallies on the bore beside and above the part."""
    scene = build_scene(design, collimator, excitation_filter=False)
    lay = _unit_layout(design, collimator)
    top = float(collimator.mesh.bounds[1, 2])
    hx, hy = lay.bore_x - TALLY_INSET_MM, lay.bore_y - TALLY_INSET_MM
    tallies = []
    for unit, matrix in enumerate(scene.poses):
        for zone, z0, z1 in ((Zone.BORE_BESIDE_PART, BOARD_Z_MM, top), (Zone.BORE_ABOVE_PART, top, lay.lip_z0)):
            v, fc = _quads(_walls(hx, hy, z0 + TALLY_INSET_MM, z1 - TALLY_INSET_MM))
            tallies.append(Part(f"{zone.name.lower()}_{unit}", _place(matrix, v), fc, Role.ABSORBER, absorber=zone))
    return dataclasses.replace(scene, parts=scene.parts + tuple(tallies))


def _angles(record, scene) -> np.ndarray:
    axis = scene.unit_axes[record.unit]
    cos_axis = np.einsum("ij,ij->i", np.nan_to_num(record.exit_direction), axis)
    return np.degrees(np.arccos(np.clip(cos_axis, -1.0, 1.0)))


def _families(scene, setup, rays: int, seed: int, cavity_radius_mm: float, collimator) -> np.ndarray:
    batch = emit_rays(scene, setup.source, rays, seed)
    family = np.empty(len(batch.unit), dtype=object)
    for unit, pose in enumerate(scene.poses):
        pick = batch.unit == unit
        inverse = np.linalg.inv(pose)
        origin = batch.origin_mm[pick] @ inverse[:3, :3].T + inverse[:3, 3]
        family[pick] = first_surfaces(collimator, origin, batch.direction[pick] @ inverse[:3, :3].T, cavity_radius_mm)
    return family


def unit_losses(design, collimator, cavity_radius_mm: float, setup, rays: int, seed: int) -> dict:
    """The table of one part: fates by family (fractions of the LEDs' power)."""
    scene = zoned_scene(design, collimator)
    record = trace(scene, setup.source, rays, transmission=setup.transmission, seed=seed)
    family = _families(scene, setup, rays, seed, cavity_radius_mm, collimator)
    absorbed = int(Status.ABSORBED)
    left = np.isin(record.status, [int(Status.SAMPLE), int(Status.ESCAPED)]) | (
        record.status == absorbed + int(Absorber.IMAGING_TOWER)
    )
    fates = {
        "left the unit": left,
        "bore beside the part": record.status == absorbed + int(Zone.BORE_BESIDE_PART),
        "bore above the part": record.status == absorbed + int(Zone.BORE_ABOVE_PART),
        "lip": record.status == absorbed + int(Absorber.HOUSING),
        "LED board": record.status == absorbed + int(Absorber.LED_BOARD),
        "truncated": record.status == int(Status.TRUNCATED),
    }
    angle = _angles(record, scene)
    rows = {}
    for name in ("all", *FAMILIES):
        pick = np.ones(record.rays, bool) if name == "all" else family == name
        if not pick.any():
            continue
        out = pick & left
        rows[name] = {
            "share": round(float(pick.mean()), 4),
            **{fate: round(float((pick & mask).mean()), 4) for fate, mask in fates.items()},
            "exit_angle_deg_p50_p90": (
                [round(float(v), 1) for v in np.percentile(angle[out], [50, 90])] if out.any() else None
            ),
            "left_within_15deg": round(float((out & (angle <= 15.0)).mean()), 4),
        }
    bare = build_scene(design, collimator, excitation_filter=False, housing=False)
    free = trace(bare, setup.source, rays, transmission=setup.transmission, seed=seed)
    forward = free.passed
    bare_angle = _angles(free, bare)
    return {
        "part": collimator.label,
        "top_mm": round(float(collimator.mesh.bounds[1, 2]), 3),
        "cavity_radius_mm": cavity_radius_mm,
        "bare_forward": round(float(forward.mean()), 4),
        "bare_within_30deg": round(float((forward & (bare_angle <= 30.0)).mean()), 4),
        "bare_back_to_board": round(float((~forward & (free.status == absorbed + int(Absorber.LED_BOARD))).mean()), 4),
        "stderr": round(math.sqrt(0.25 / rays), 4),
        "families": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--design", action="append", default=[], help="design YAML whose own part to add (repeatable)")
    parser.add_argument("--rays", type=int, default=400_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON file for the table")
    args = parser.parse_args()
    if args.out:  # never over one of its own inputs (an existing table is replaced)
        try:
            check_output(args.out, command="illum_unit_losses", inputs=args.design, overwrite=True)
        except OutputError as error:
            parser.error(str(error))

    v2 = load_preset("cm2-v2")
    setup, authors = reference_inputs(v2)
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import PAPER_COLLIMATOR  # a 2.0-mm excitation gap: the authors' 2.0-mm part under its filter

    parts = [(v2.with_changes(PAPER_COLLIMATOR), authors, AUTHORS_CAVITY_RADIUS_MM)]
    for path in ["cm2-v2", str(ROOT / "benchmarks" / "designs" / "cm2-v2-cone-wall.yaml"), *args.design]:
        design = load_preset(path)
        part = dataclasses.replace(collimator_from_design(design), label=f"{Path(path).stem} (CAD)")
        parts.append((design, part, design.collimator.cavity_radius_mm))
    table = []
    for design, part, radius in parts:
        table.append(unit_losses(design, part, radius, setup, args.rays, args.seed))
        print(json.dumps(table[-1]), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(table, indent=1))


if __name__ == "__main__":
    main()
