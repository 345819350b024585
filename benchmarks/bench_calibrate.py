"""Benchmark: `cm2 calibrate scan` on a traced scan with an undeclared effect, and the in-place
perturbation of traced foci against a fresh trace of every perturbed design, in the same run.

1. The scan (made once, kept in ``--work``): ``cm2 psf simulate``'s path
   (:func:`cm2optics.emission.scan.simulate_scan`, the default Gaussian pinhole) on the design with
   ``--effect`` written into its ``as_built`` section, then a realistic sensor
   (:func:`cm2optics.calibrate.noise.add_scan_noise`: shot noise at scan.yaml's gain, ``--read-noise``
   counts of read noise, a 100-count dark level, 12-bit clipping).
2. The timed run: :func:`cm2optics.calibrate.scan.calibrate_scan` against the *nominal* design,
   wall seconds from reading the scan to the finished document (the issue's target: a 9×9×5
   scan at 4× binning, 405 positions, attributed in ≤ 10 min on this 2-core machine).
3. The reference: one perturbed design (an MLA rotation) evaluated at the fit positions both
   ways: a fresh trace of the rotated design (what every finite difference cost before) and
   :meth:`~cm2optics.calibrate.tracer.TracerSimulator.rates` moving the cached traced foci; their
   ratio, and the NMSE between the two images.

Printed: the effects found, NMSE and χ² before and after, the wall time and the load average.

    .venv/bin/python benchmarks/bench_calibrate.py --grid 9x9x5 --binning 4 --work /tmp/bench-cal
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from pathlib import Path

import numpy as np

from cm2optics.calibrate.noise import add_scan_noise
from cm2optics.calibrate.scan import calibrate_scan, fit_subset, scan_source
from cm2optics.calibrate.tracer import TracerSimulator, design_with
from cm2optics.design import load_preset
from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, simulate_scan
from cm2optics.formats.scan import read_scan


def make_scan(args: argparse.Namespace, design, work: Path) -> Path:
    """The noisy scan of the design with the undeclared effect (made once per settings)."""
    field, _, value = args.effect.partition("=")
    name = f"{args.grid}-b{args.binning}-{field}-{value}-r{args.read_noise:g}-s{args.seed}"
    noisy = work / f"noisy-{name}"
    if noisy.is_dir():
        return noisy
    built = design.with_changes({f"as_built.{field}": json.loads(value)}) if field else design
    counts = tuple(int(n) for n in args.grid.split("x"))
    positions = calibration_grid_mm(design, counts, field_mm=args.field_mm, depth_mm=args.depth_mm)
    clean = work / f"clean-{name}"
    start = time.perf_counter()
    settings = ScanSettings(psf=PSFSettings(binning=args.binning))
    simulate_scan(built, positions, clean, settings, workers=args.workers, progress=False)
    print(f"scan simulated: {len(positions)} positions in {time.perf_counter() - start:.0f} s")
    return add_scan_noise(clean, noisy, read_noise_counts=args.read_noise, dark_level=100.0, seed=args.seed)


def reference(design, scan_dir: Path, fit_positions: int) -> None:
    """One rotated design at the fit positions: a fresh trace against the in-place perturbation."""
    scan = read_scan(scan_dir)
    source, _ = scan_source(scan.meta.extra)
    positions = scan.positions_mm[fit_subset(scan.positions_mm, fit_positions)]
    simulator = TracerSimulator(design, binning=scan.meta.binning, source=source)
    start = time.perf_counter()
    simulator.rates(positions, {})
    first = time.perf_counter() - start
    values = {"mla_rotation": {"angle_deg": 0.3}}
    start = time.perf_counter()
    fast = simulator.rates(positions, values)
    moved = time.perf_counter() - start
    start = time.perf_counter()
    rotated = design_with(design, values)
    model = EmissionModel(rotated, source, settings=PSFSettings(binning=scan.meta.binning))
    traced = np.stack([model.image(p) * 1e6 for p in positions])
    fresh = time.perf_counter() - start
    nmse = float(np.sum((fast - traced) ** 2) / np.sum(traced**2))
    print(
        f"one perturbed design at {len(positions)} positions: fresh trace {fresh:.2f} s, in place {moved:.3f} s "
        f"({fresh / moved:.0f}x); first (nominal) trace with ePSFs {first:.2f} s; NMSE in place vs trace {nmse:.1e}"
    )


def timestamped(start: float):
    """A progress callback printing the seconds since ``start`` before each message."""
    return lambda message: print(f"{time.perf_counter() - start:7.1f} s  {message}", flush=True)


def _children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished child processes."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", default="9x9x5", help="NXxNYxNZ positions")
    parser.add_argument("--binning", type=int, default=4)
    parser.add_argument("--field-mm", type=float, default=None, help="lateral extent, mm (default: the design's)")
    parser.add_argument("--depth-mm", type=float, default=None, help="axial extent, mm (default: the design's)")
    parser.add_argument("--effect", default="mla_rotation_deg=0.5", help="as_built FIELD=VALUE injected, undeclared")
    parser.add_argument("--read-noise", type=float, default=2.0, help="read noise, counts")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--fit-positions", type=int, default=27)
    parser.add_argument("--workers", type=int, default=2, help="processes simulating the scan and tracing the model")
    parser.add_argument("--work", type=Path, default=Path("out/bench-calibrate"), help="where the scans are kept")
    parser.add_argument("--skip-reference", action="store_true")
    args = parser.parse_args()

    design = load_preset("cm2-v2")
    args.work.mkdir(parents=True, exist_ok=True)
    scan_dir = make_scan(args, design, args.work)
    load = os.getloadavg()[0]
    start = time.perf_counter()
    cpu, children = time.process_time(), _children_cpu()
    result = calibrate_scan(
        scan_dir, design, fit_positions=args.fit_positions, workers=args.workers, progress=timestamped(start)
    )
    wall = time.perf_counter() - start
    doc = result.document
    summary = {k: doc[k] for k in ("effects", "nmse_before", "nmse_after", "chi2_before", "chi2_after", "unexplained")}
    print(json.dumps(summary, indent=1, ensure_ascii=False))
    print(
        f"calibrate_scan: {len(result.before.files)} positions at binning {result.before.residual_counts.shape} "
        f"in {wall:.0f} s (load {load:.1f} → {os.getloadavg()[0]:.1f}); CPU of this process "
        f"{time.process_time() - cpu:.0f} s, of its finished worker processes {_children_cpu() - children:.0f} s"
    )
    if not args.skip_reference:
        reference(design, scan_dir, args.fit_positions)


if __name__ == "__main__":
    main()
