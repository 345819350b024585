"""Held-out accuracy of the 3D-LSV model between its calibration nodes (issue 13): single
emitters at random sub-pixel positions (seeded, off the calibration grid), traced by the emission
module, against the model with a whole-pixel basis (``--oversample 1``), an ePSF basis from the
synthetic scan's ``epsf.h5`` (``--oversample 4``) and an ePSF basis estimated from the
whole-pixel frames only (the same scan without ``epsf.h5``, as a lab would have it), beside the
depth-wise LSI baseline; on axis and at r = 1, 2, 3 mm, per binning.

1. **Scan**: ``cm2 psf simulate --grid G --binning B --oversample 4 --profile isotropic
   --pinhole-um D`` (a D-µm bead, the emitters' own kind of source), reused when present.
2. **Models**: ``cm2 lsv build`` with ``--oversample 1`` and ``--oversample 4`` on the scan, and
   ``--oversample 4`` on a copy of the scan without ``epsf.h5`` (the estimate), each interpolating
   along the focal surface and turning the lateral neighbours with the azimuth where the scan
   says so (the defaults), and ``--oversample 4`` with ``--rotate off`` (fixed orientation) and
   with ``--fixed-depth --rotate off`` beside them.
3. **Emitters** (``--per-radius`` per radius, seed ``--seed``): on axis = within ±20 µm of the
   axis (random sub-pixel phase), off axis at radius r along a random angle; z uniform over the
   inner 80 % of the scanned depth. *Traced*: the library call behind ``cm2 psf image``
   (:func:`cm2optics.emission.image.render_emitters`, float, no 16-bit rounding; ``--via-cli``
   runs the command itself). *Models*: :meth:`LSVModel.point_image` (exact sub-pixel placement).

Error per emitter: ‖m − t/u‖ / ‖t/u‖ with u the total of the traced emitter at the point where the
model is scaled to a unit total (the in-focus on-axis point, clamped into the model's grid: for a
patch scan off axis, its node nearest that point), plus the shape error (best scale) and the flux
ratio.

**Patch scans** (the node density needed, measured): ``--patch-center-mm X,Y --patch-spacing-mm H``
scans ``--patch-nodes`` × ``--patch-nodes`` lateral nodes H apart around (X, Y) at ``--patch-depths``
depths ``--patch-axial-mm`` apart around the focal plane (``cm2 psf simulate --positions``; a
patch off the axis gets the column x = 0 and row y = 0 as well, from which the build fits the
geometry: the foci of a point 3 mm off the axis are not all on the sensor) and
draws the emitters inside the patch's central half (x, y uniform, z uniform over the inner 80 % of
the depths), one group; ``X,Y,Z`` centres its depths on Z (z = 0 is added for the geometry fit).
An existing patch scan is reused with ``--scan`` and the same patch options (they draw the
emitters); a model file already in ``OUT/binB/`` (e.g. linked from an earlier run) is not rebuilt. ``--extra-model NAME=PATH`` (repeatable) compares further models (e.g.
one from the full-field scan) on the same emitters. ``--split`` adds, for every ePSF model, the
parts of its error at each emitter: the emitter's own traced ePSF placed as the model places its
PSFs (``| traced ePSF``: the sub-pixel placement and the crop window, the floor), that ePSF fitted by
the model's basis lenslet by lenslet (``| on basis``: + the low rank); the model's own figure adds
the interpolation of the coefficients between the nodes.

    python benchmarks/bench_lsv_heldout.py --binning 2 --grid 9x9x11 --out /tmp/heldout
    python benchmarks/bench_lsv_heldout.py --patch-center-mm 3,0 --patch-spacing-mm 0.2 --variants whole,epsf --out /tmp/p3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from cm2optics.lsv.validate import image_errors

CLI = [sys.executable, "-m", "cm2optics.cli"]


def run(args: list[str]) -> dict:
    result = subprocess.run(CLI + args + ["--json"], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"cm2 {' '.join(args)} failed ({result.returncode}):\n{result.stderr[-3000:]}")
    return json.loads(result.stdout)


def patch_positions(args: argparse.Namespace) -> np.ndarray:
    """(N, 3) x, y, z (mm) of the patch scan: a full grid around ``--patch-center-mm``, with x = 0,
    y = 0 and z = 0 added where the patch lacks them (the build fits the geometry from the on-axis
    stack, whose in-focus image must show all the foci)."""
    lateral = args.patch_spacing_mm * (np.arange(args.patch_nodes) - (args.patch_nodes - 1) / 2)
    axial = args.patch_axial_mm * (np.arange(args.patch_depths) - (args.patch_depths - 1) / 2)
    offsets = (lateral, lateral, axial)
    xs, ys, zs = (np.union1d(np.round(c + d, 6), [0.0]) for c, d in zip(patch_center(args), offsets, strict=True))
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    return np.round(np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1), 6)


def patch_center(args: argparse.Namespace) -> tuple[float, float, float]:
    """``--patch-center-mm`` as (x, y, z) mm (z = 0 when it gives only X,Y)."""
    values = [float(v) for v in args.patch_center_mm.split(",")]
    if len(values) not in (2, 3):
        raise SystemExit(f"--patch-center-mm {args.patch_center_mm!r}: give X,Y or X,Y,Z (mm)")
    return (*values, 0.0) if len(values) == 2 else tuple(values)


def emitters(args: argparse.Namespace, zs: tuple[float, float]) -> list[tuple[str, float, tuple[float, float, float]]]:
    """Seeded emitter positions (mm): per radius of ``--radii``, or inside the patch of a patch scan."""
    rng = np.random.default_rng(args.seed)
    z0, z1 = zs
    margin = 0.1 * (z1 - z0)
    out = []
    if args.patch_center_mm:
        cx, cy, cz = patch_center(args)
        half = args.patch_spacing_mm * (args.patch_nodes - 1) / 4  # the patch's central half
        depth = 0.8 * args.patch_axial_mm * (args.patch_depths - 1) / 2  # the inner 80 % of its depths
        for _ in range(args.per_radius):
            x, y = (c + float(v) for c, v in zip((cx, cy), rng.uniform(-half, half, 2), strict=True))
            z = float(rng.uniform(cz - depth, cz + depth))
            group = f"patch {args.patch_center_mm} mm, {args.patch_spacing_mm:g} mm"
            out.append((group, math.hypot(cx, cy), (round(x, 6), round(y, 6), round(z, 6))))
        return out
    for r in [float(v) for v in args.radii.split(",")]:
        for _ in range(args.per_radius):
            z = float(rng.uniform(z0 + margin, z1 - margin))
            if r == 0:
                x, y = (float(v) for v in rng.uniform(-0.02, 0.02, 2))
            else:
                lo, hi = (math.radians(float(v)) for v in args.angles_deg.split(","))
                angle = rng.uniform(lo, hi)
                x, y = r * math.cos(angle), r * math.sin(angle)
            out.append((f"r={r:g}", r, (round(x, 6), round(y, 6), round(z, 6))))
    return out


def traced(design, binning: int, position, diameter_um: float, via_cli: bool, folder: Path) -> np.ndarray:
    from cm2optics.emission.image import render_emitters
    from cm2optics.emission.psf import PSFSettings
    from cm2optics.formats.emitters import Emitters

    x, y, z = position
    if via_cli:
        import tifffile
        import yaml

        csv = folder / "emitter.csv"
        csv.write_text(f"x_um,y_um,z_um,diameter_um,intensity\n{x * 1e3},{y * 1e3},{z * 1e3},{diameter_um},1\n")
        tif = folder / "traced.tif"
        run(["psf", "image", "--emitters", str(csv), "--binning", str(binning), "--out", str(tif)])
        sidecar = yaml.safe_load(tif.with_suffix(".yaml").read_text())
        counts = tifffile.imread(tif).astype(np.float64)
        return (counts - float(sidecar.get("dark_level", 0.0) or 0.0)) / float(sidecar["counts_per_unit"])
    table = Emitters.from_positions_um(np.array([[x * 1e3, y * 1e3, z * 1e3]]), np.array([diameter_um]), np.ones(1))
    return render_emitters(design, table, PSFSettings(binning=binning))


_EMISSION: dict = {}


def traced_epsf(design, binning: int, position, diameter_um: float, model) -> np.ndarray:
    """(J, h·S, w·S) the traced ePSF of the emitter at ``position`` (mm; what ``cm2 psf simulate
    --oversample S`` writes to epsf.h5, in the traced image's units), registered on each focus's
    chief ray in the frame of ``model``'s basis (as :func:`cm2optics.lsv.epsf.epsf_crops`)."""
    from cm2optics.emission.psf import EmissionModel, PSFSettings
    from cm2optics.emission.source import fluorescent_bead
    from cm2optics.lsv.kernels import sample_window

    S = model.oversample
    key = (binning, S, diameter_um)
    if key not in _EMISSION:
        _EMISSION.clear()
        _EMISSION[key] = EmissionModel(
            design, fluorescent_bead(diameter_um), settings=PSFSettings(binning=binning, oversample=S)
        )
    foci = _EMISSION[key].foci(np.asarray(position, float))
    r0, c0 = min(f.row0 for f in foci) * S, min(f.col0 for f in foci) * S
    r1 = max(f.row0 * S + f.epsf.shape[0] for f in foci)
    c1 = max(f.col0 * S + f.epsf.shape[1] for f in foci)
    canvas = np.zeros((r1 - r0, c1 - c0))
    for f in foci:
        r, c = f.row0 * S - r0, f.col0 * S - c0
        canvas[r : r + f.epsf.shape[0], c : c + f.epsf.shape[1]] += f.epsf
    h, w = model.patch_shape
    centres = model.geometry.focus(*position)
    return np.stack(
        [
            sample_window(canvas, (centres[j, 0] * S - r0, centres[j, 1] * S - c0), (h * S, w * S))
            for j in range(len(centres))
        ]
    )


def split_errors(model, truth: np.ndarray, position, target: np.ndarray) -> dict[str, dict[str, float]]:
    """The parts of an ePSF model's error at one emitter (issue 13): its traced ePSF ``truth``
    (J, h·S, w·S, in the units of ``target``) placed as the model places its own (the sub-pixel
    placement and the window: the floor), and its fit by the model's basis, lenslet by lenslet
    (+ the low rank); the model itself adds the interpolation between the nodes."""
    from cm2optics.lsv.sparse import place_patches

    return {
        "traced ePSF": image_errors(place_patches(model, truth, *position), target),
        "on basis": image_errors(place_patches(model, model.project(truth), *position), target),
    }


def bench_binning(args: argparse.Namespace, binning: int, design) -> dict:
    from cm2optics.lsv.lsi import lsi_model
    from cm2optics.lsv.model import load_model

    root = Path(args.out) / f"bin{binning}"
    scan = root / "scan"
    root.mkdir(parents=True, exist_ok=True)
    seconds = {}
    if args.scan and not scan.exists():
        scan.symlink_to(Path(args.scan).resolve())
    if not (scan / "epsf.h5").is_file():
        start = time.perf_counter()
        command = ["psf", "simulate", "--binning", str(binning), "--oversample", "4"]
        if args.patch_center_mm:
            csv = root / "patch_positions.csv"
            np.savetxt(csv, patch_positions(args), fmt="%.6f", delimiter=",", header="x_mm,y_mm,z_mm", comments="")
            command += ["--positions", str(csv)]
        else:
            command += ["--grid", args.grid]
        command += ["--profile", "isotropic", "--pinhole-um", str(args.diameter_um), "--out", str(scan)]
        if args.workers:
            command += ["--workers", str(args.workers)]
        run(command)
        seconds["scan"] = time.perf_counter() - start
    # the measured-style copy: frames only
    frames = root / "scan_frames_only"
    if not frames.exists():
        frames.mkdir()
        for item in scan.iterdir():
            if item.name != "epsf.h5":
                (frames / item.name).symlink_to(item.resolve())
    builds = {  # name: variant, scan folder, oversample, interpolation (build options)
        "oversample 1": ("whole", scan, 1, ["--focal-surface"]),
        "oversample 4 (synthetic ePSF), fixed depth": ("fixed-depth", scan, 4, ["--fixed-depth", "--rotate", "off"]),
        "oversample 4 (synthetic ePSF), fixed orientation": (
            "fixed-orientation", scan, 4, ["--focal-surface", "--rotate", "off"],
        ),
        "oversample 4 (synthetic ePSF)": ("epsf", scan, 4, ["--focal-surface"]),
        "oversample 4 (estimated from frames)": ("estimated", frames, 4, ["--focal-surface"]),
    }  # fmt: skip
    variants = set(args.variants.split(","))
    models, build_info = {}, {}
    for name, (variant, folder, S, interpolation) in builds.items():
        if variant not in variants:
            continue
        path = root / f"model_S{S}_{folder.name}_{'_'.join(a.strip('-') for a in interpolation)}.h5"
        if not path.is_file():
            start = time.perf_counter()
            command = ["lsv", "build", str(folder), "--rank", str(args.rank), "--oversample", str(S), "--no-report"]
            command += ["--out", str(path), *interpolation]
            if args.patch_px:
                command += ["--patch-px", str(args.patch_px)]
            run(command)
            seconds[f"build {name}"] = time.perf_counter() - start
        models[name] = load_model(path)
        provenance = models[name].provenance  # also for a model built by an earlier run
        keys = ("svd", "epsf", "focal_surface", "rotation", "seconds")
        build_info[name] = {"model": str(path), **{k: provenance.get(k) for k in keys}}
    if "oversample 1" in models:
        models["LSI"] = lsi_model(models["oversample 1"])
    for extra in args.extra_model:
        name, _, path = extra.partition("=")
        models[name] = load_model(Path(path))
    zs = next(iter(models.values())).grid_z_mm
    units = {}  # the traced total at each model's unit point (x, y, z mm)
    for model in models.values():
        reference = unit_point(model)
        if reference not in units:
            units[reference] = float(traced(design, binning, reference, args.diameter_um, args.via_cli, root).sum())
    rows = []
    start = time.perf_counter()
    for group, r, position in emitters(args, (float(zs[0]), float(zs[-1]))):
        t = traced(design, binning, position, args.diameter_um, args.via_cli, root)
        row = {"group": group, "r_mm": r, "position_mm": position}
        for name, model in list(models.items()):
            row[name] = image_errors(model.point_image(*position), t / units[unit_point(model)])
            if args.split and model.oversample > 1:
                truth = traced_epsf(design, binning, position, args.diameter_um, model) / units[unit_point(model)]
                for part, value in split_errors(model, truth, position, t / units[unit_point(model)]).items():
                    row[f"{name} | {part}"] = value
        rows.append(row)
        print(
            f"  bin {binning} {group:6s} {position}: "
            + "  ".join(
                f"{name.split(' (')[0][:12]}{'*' if 'estimated' in name else ''} {row[name]['error']:.3f}"
                for name in models
            )
            + "".join(f"  [{k}] {v['error']:.3f}" for k, v in row.items() if " | " in k),
            flush=True,
        )
    seconds["emitters"] = time.perf_counter() - start
    summary = {}
    columns = list(dict.fromkeys(k for r in rows for k in r if k not in ("group", "r_mm", "position_mm")))
    for group in dict.fromkeys(r["group"] for r in rows):
        members = [r for r in rows if r["group"] == group]
        summary[group] = {
            name: {
                "error": float(np.mean([m[name]["error"] for m in members])),
                "error_min": float(np.min([m[name]["error"] for m in members])),
                "error_max": float(np.max([m[name]["error"] for m in members])),
                "shape_error": float(np.mean([m[name]["shape_error"] for m in members])),
                "flux_ratio": float(np.mean([m[name]["flux_ratio"] for m in members])),
                "emitters": len(members),
            }
            for name in columns
        }
    units_json = {str(k): v for k, v in units.items()}
    return {
        "binning": binning, "summary": summary, "rows": rows, "builds": build_info, "seconds": seconds,
        "units": units_json,
    }  # fmt: skip


def unit_point(model) -> tuple[float, float, float]:
    """The point (x, y, z mm) whose image the model scales to a unit total: the in-focus on-axis
    point clamped into its calibration grid."""
    axes = (model.grid_x_mm, model.grid_y_mm, model.grid_z_mm)
    return tuple(float(np.clip(0.0, axis[0], axis[-1])) for axis in axes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--binning", default="2", help="comma-separated binnings (e.g. 1,2)")
    parser.add_argument("--grid", default="9x9x11")
    parser.add_argument("--rank", type=int, default=64)
    parser.add_argument("--patch-px", type=int, default=56, help="crop side (px of the binned frames)")
    parser.add_argument("--radii", default="0,1,2,3")
    parser.add_argument("--per-radius", type=int, default=3)
    parser.add_argument("--diameter-um", type=float, default=2.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--angles-deg", default="0,360", help="range of the off-axis emitters' angles, degrees")
    parser.add_argument(
        "--scan", help="use this scan folder (made with `cm2 psf simulate --oversample 4`) instead of simulating one"
    )
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--variants",
        default="whole,fixed-depth,fixed-orientation,epsf,estimated",
        help="models to build: whole (oversample 1, with the LSI baseline), fixed-depth, fixed-orientation, "
        "epsf (synthetic ePSF, the defaults), estimated (ePSF estimated from the frames)",
    )
    parser.add_argument("--patch-center-mm", help="X,Y or X,Y,Z: scan a patch around this point instead of --grid")
    parser.add_argument("--patch-spacing-mm", type=float, default=0.2, help="lateral node spacing of the patch")
    parser.add_argument("--patch-nodes", type=int, default=5, help="lateral nodes per side of the patch")
    parser.add_argument("--patch-depths", type=int, default=5, help="depths of the patch")
    parser.add_argument("--patch-axial-mm", type=float, default=0.1, help="axial node spacing of the patch")
    parser.add_argument(
        "--extra-model", action="append", default=[], help="NAME=PATH: a further model to compare (repeatable)"
    )
    parser.add_argument("--via-cli", action="store_true", help="trace through `cm2 psf image` (16-bit files)")
    parser.add_argument(
        "--split",
        action="store_true",
        help="for each ePSF model also the emitter's traced ePSF placed as the model places its own (the "
        "floor) and its fit by the model's basis (+ the low rank): the model adds the interpolation",
    )
    parser.add_argument("--out", default="out/bench-lsv-heldout")
    args = parser.parse_args()
    from cm2optics.design import load_preset

    design = load_preset("cm2-v2")
    results = []
    for binning in [int(v) for v in args.binning.split(",")]:
        results.append(bench_binning(args, binning, design))
    report = {
        "machine": f"{platform.node()} {platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load": " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "n/a",
        "args": vars(args),
        "results": results,
    }
    out = Path(args.out)
    (out / "results.json").write_text(json.dumps(report, indent=2))
    for result in results:
        print(f"\nbinning {result['binning']}: mean error ‖m − t‖/‖t‖ (flux included) per radius")
        names = list(next(iter(result["summary"].values())))
        print("| r | " + " | ".join(n.replace(" | ", ": ") for n in names) + " |")
        print("|---|" + "---|" * len(names))
        for group, values in result["summary"].items():
            print(f"| {group} | " + " | ".join(f"{values[n]['error']:.3f}" for n in names) + " |")
    shutil.rmtree(out / "tmp", ignore_errors=True)


if __name__ == "__main__":
    main()
