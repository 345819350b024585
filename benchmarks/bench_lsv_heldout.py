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

Error per emitter: ‖m − t/u‖ / ‖t/u‖ with u the total of the traced in-focus on-axis emitter
(the model's unit: flux counts), plus the shape error (best scale) and the flux ratio.

    python benchmarks/bench_lsv_heldout.py --binning 2 --grid 9x9x11 --out /tmp/heldout
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


def emitters(args: argparse.Namespace, zs: tuple[float, float]) -> list[tuple[str, float, tuple[float, float, float]]]:
    rng = np.random.default_rng(args.seed)
    z0, z1 = zs
    margin = 0.1 * (z1 - z0)
    out = []
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
        command = ["psf", "simulate", "--grid", args.grid, "--binning", str(binning), "--oversample", "4"]
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
    builds = {  # name: scan folder, oversample, interpolation (build options)
        "oversample 1": (scan, 1, ["--focal-surface"]),
        "oversample 4 (synthetic ePSF), fixed depth": (scan, 4, ["--fixed-depth", "--rotate", "off"]),
        "oversample 4 (synthetic ePSF), fixed orientation": (scan, 4, ["--focal-surface", "--rotate", "off"]),
        "oversample 4 (synthetic ePSF)": (scan, 4, ["--focal-surface"]),
        "oversample 4 (estimated from frames)": (frames, 4, ["--focal-surface"]),
    }
    if args.skip_estimate:
        del builds["oversample 4 (estimated from frames)"]
    models, build_info = {}, {}
    for name, (folder, S, interpolation) in builds.items():
        path = root / f"model_S{S}_{folder.name}_{'_'.join(a.strip('-') for a in interpolation)}.h5"
        if not path.is_file():
            start = time.perf_counter()
            command = ["lsv", "build", str(folder), "--rank", str(args.rank), "--oversample", str(S), "--no-report"]
            command += ["--out", str(path), *interpolation]
            if args.patch_px:
                command += ["--patch-px", str(args.patch_px)]
            summary = run(command)
            seconds[f"build {name}"] = time.perf_counter() - start
            keys = ("nmse_calibration", "patch_px", "epsf", "focal_surface", "rotation")
            build_info[name] = {k: summary.get(k) for k in keys}
        models[name] = load_model(path)
    models["LSI"] = lsi_model(models["oversample 1"])
    zs = models["oversample 1"].grid_z_mm
    unit = float(traced(design, binning, (0.0, 0.0, 0.0), args.diameter_um, args.via_cli, root).sum())
    rows = []
    start = time.perf_counter()
    for group, r, position in emitters(args, (float(zs[0]), float(zs[-1]))):
        t = traced(design, binning, position, args.diameter_um, args.via_cli, root) / unit
        row = {"group": group, "r_mm": r, "position_mm": position}
        for name, model in models.items():
            row[name] = image_errors(model.point_image(*position), t)
        rows.append(row)
        print(
            f"  bin {binning} {group:6s} {position}: "
            + "  ".join(
                f"{name.split(' (')[0][:12]}{'*' if 'estimated' in name else ''} {row[name]['error']:.3f}"
                for name in models
            ),
            flush=True,
        )
    seconds["emitters"] = time.perf_counter() - start
    summary = {}
    for group in dict.fromkeys(r["group"] for r in rows):
        members = [r for r in rows if r["group"] == group]
        summary[group] = {
            name: {
                "error": float(np.mean([m[name]["error"] for m in members])),
                "shape_error": float(np.mean([m[name]["shape_error"] for m in members])),
                "flux_ratio": float(np.mean([m[name]["flux_ratio"] for m in members])),
            }
            for name in models
        }
    return {"binning": binning, "summary": summary, "rows": rows, "builds": build_info, "seconds": seconds}


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
    parser.add_argument("--skip-estimate", action="store_true", help="leave out the basis estimated from frames")
    parser.add_argument("--via-cli", action="store_true", help="trace through `cm2 psf image` (16-bit files)")
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
        print("| r | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for group, values in result["summary"].items():
            print(f"| {group} | " + " | ".join(f"{values[n]['error']:.3f}" for n in names) + " |")
    shutil.rmtree(out / "tmp", ignore_errors=True)


if __name__ == "__main__":
    main()
