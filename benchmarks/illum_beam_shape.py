"""The beam the freeform bound asks for, beside the beam today's part sends (issue 16).

:func:`~cm2optics.illumination.bounds.uniform_beam_bound` with ``freeform=True,
before_filter=True`` and the finite LED returns the best beam of any shape (the same from every
unit) as weights on cells of direction in each unit's frame: x across the unit's plane of tilt,
y in it (+y: the side of the axis that lands further from the unit). Its shape is summarised by
the centroid, the RMS widths along x and y and the share within 10–40° of the axis — for the
weights as the LP gives them (the beam's aim before the étendue blur) and for the beam after the
finite LED's blur (:func:`~cm2optics.illumination.bounds.etendue_blur_rad`, what the unit would
send) — and compared with the enclosed-die part's beam traced without the filter, binned on the
same cells. The authors' LED profile, spectrum and excitation coating table throughout.

    .venv/bin/python benchmarks/illum_beam_shape.py --rays 200000 --out shape.json --png shape.png
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from illum_filter_lever import ENCLOSED
from illum_ray_families import reference_inputs

from cm2optics.design import load_preset
from cm2optics.formats.outputs import OutputError, check_output
from cm2optics.illumination.bounds import blur_directions, etendue_blur_rad, uniform_beam_bound
from cm2optics.illumination.geometry import build_scene, collimator_from_design
from cm2optics.illumination.tracer import trace
from cm2optics.optics.layout import led_poses

#: Placements compared: the enclosed part's own and the free-aim freeform bound's best (BENCHMARKS, session 12).
PLACEMENTS = {
    "own (44° / +1.75 / 7.5 mm)": {},
    "free-aim best (40° / +2.0 / 6.7 mm)": {
        "led_array.tilt_deg": 40.0,
        "led_array.aim_mm": 2.0,
        "led_array.offset_mm": 6.7,
    },
}
CELLS = 24
MAX_ANGLE_DEG = 50.0


def shape(tan_xy: np.ndarray, weight: np.ndarray) -> dict:
    """Centroid and RMS widths (degrees, as atan of the tangent-plane moments) of a beam given as
    directions ``tan_xy`` (n, 2) in the unit's tangent plane with weights, and its share within
    10–40° of the axis."""
    w = weight / weight.sum()
    mean = w @ tan_xy
    rms = np.sqrt(w @ (tan_xy - mean) ** 2)
    angle = np.degrees(np.arctan(np.hypot(tan_xy[:, 0], tan_xy[:, 1])))
    return {
        "centroid_x_deg": round(math.degrees(math.atan(mean[0])), 2),
        "centroid_y_deg": round(math.degrees(math.atan(mean[1])), 2),
        "rms_x_deg": round(math.degrees(math.atan(rms[0])), 2),
        "rms_y_deg": round(math.degrees(math.atan(rms[1])), 2),
        "within_deg": {f"{a}": round(float(w[angle <= a].sum()), 3) for a in (10, 20, 30, 40)},
        "p50_p90_deg": [round(float(v), 1) for v in np.percentile(angle, [50, 90], weights=w, method="inverted_cdf")],
    }


def blurred(design, centres_tan: np.ndarray, profile: np.ndarray, samples: int, rng: np.random.Generator) -> np.ndarray:
    """Directions (samples, 2; tangent plane) of the bound's beam after the finite LED's étendue blur:
    drawn from the cells' weights, uniform within a cell, each turned at random within the blur
    cone (uniform radiance) by the bound's own blur."""
    side = 2 * math.tan(math.radians(MAX_ANGLE_DEG)) / CELLS
    pick = rng.choice(len(profile), samples, p=profile / profile.sum())
    tan_xy = centres_tan[pick] + rng.uniform(-side / 2, side / 2, (samples, 2))
    direction = np.column_stack([tan_xy, np.ones(samples)])
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    turned = blur_directions(direction, etendue_blur_rad(design), rng)
    return turned[:, :2] / turned[:, 2:]


def traced_beam(design, setup, rays: int, seed: int) -> tuple[np.ndarray, float]:
    """(directions in each unit's tangent plane (n, 2), share of the LED's light reaching the
    filter) of the part traced without its filter."""
    scene = build_scene(design, collimator_from_design(design), excitation_filter=False)
    record = trace(scene, setup.source, rays, seed=seed)
    out = record.passed
    rotation = np.stack([pose.matrix[:3, :3] for pose in led_poses(design)])
    local = np.einsum("ni,nij->nj", record.exit_direction[out], rotation[record.unit[out]])
    return local[:, :2] / local[:, 2:], float(out.mean())


def write_png(path: str, panels: list[tuple[str, np.ndarray, np.ndarray]]) -> None:
    """Weights per cell of each beam on the tangent plane (x across the plane of tilt, y in it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    reach = math.tan(math.radians(MAX_ANGLE_DEG))
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.6))
    for ax, (title, tan_xy, weight) in zip(axes, panels, strict=True):
        grid, _, _ = np.histogram2d(*tan_xy.T, bins=CELLS, range=[[-reach, reach]] * 2, weights=weight / weight.sum())
        image = ax.imshow(grid.T, origin="lower", extent=[-reach, reach, -reach, reach], cmap="magma")
        fig.colorbar(image, ax=ax)
        for a in (10, 20, 30, 40):
            ax.add_patch(plt.Circle((0, 0), math.tan(math.radians(a)), fill=False, color="c", lw=0.5))
        ax.set(title=title, xlabel="tan θx (across the plane of tilt)", ylabel="tan θy (in it; + lands further)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rays", type=int, default=200_000, help="rays traced for the part's beam")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", default=None, help="JSON file for the figures")
    parser.add_argument("--png", default=None, help="PNG of the beams")
    args = parser.parse_args()
    for path in (args.out, args.png):
        if path:
            try:
                check_output(path, command="illum_beam_shape", inputs=[ENCLOSED], overwrite=True)
            except OutputError as error:
                parser.error(str(error))
    enclosed = load_preset(ENCLOSED)
    setup, _ = reference_inputs(enclosed)
    rng = np.random.default_rng(args.seed)
    report: dict = {"inputs": "authors' LED profile, spectrum and excitation coating table", "bound": {}}
    panels = []
    for name, changes in PLACEMENTS.items():
        design = enclosed.with_changes(changes) if changes else enclosed
        bound = uniform_beam_bound(
            design,
            transmission=setup.transmission,
            spectrum=setup.source.spectrum,
            finite_source=True,
            freeform=True,
            cells=CELLS,
            max_angle_deg=MAX_ANGLE_DEG,
            rays_per_ring=4000,
            before_filter=True,
        )
        centres = np.tan(np.radians(np.array(bound["cell_centres_deg"])))
        profile = np.array(bound["profile"])
        after = blurred(design, centres, profile, 400_000, rng)
        report["bound"][name] = {
            "output_bound": bound["output_bound"],
            "cv": bound["cv"],
            "aim": shape(centres, profile),
            "after_blur": shape(after, np.ones(len(after))),
        }
        panels.append((f"freeform bound, {name.split()[0]} placement: aim", centres, profile))
        panels.append(
            (f"… after the étendue blur ({math.degrees(etendue_blur_rad(design)):.1f}°)", after, np.ones(len(after)))
        )
        print(name, json.dumps(report["bound"][name]), flush=True)
    part, reaches = traced_beam(enclosed, setup, args.rays, args.seed)
    report["traced_part"] = {"rays": args.rays, "reaches_filter": round(reaches, 4), **shape(part, np.ones(len(part)))}
    print("traced part", json.dumps(report["traced_part"]), flush=True)
    panels.append(("enclosed-die part, traced (no filter)", part, np.ones(len(part))))
    if args.png:
        write_png(args.png, panels[:2] + panels[-1:])
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    json.dump(report, sys.stdout, indent=1)


if __name__ == "__main__":
    main()
