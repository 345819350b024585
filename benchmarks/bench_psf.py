"""Benchmark: our single-lenslet PSF against Optiland's FFT PSF, in the same run.

Both compute the PSF of the central lenslet of cm2-v2 (filter plate, lens, film; one wavelength)
for a point source in the nominal focal plane, after a warm-up call:

* ours: :meth:`cm2optics.emission.psf.EmissionModel.foci` for that lenslet and one band — the
  whole pipeline: coarse and fine traces (Dr.Jit), pupil on the reference sphere, Debye integral
  by FFT, pixel integration on the sensor's pixels (2.4 µm for cm2-v2);
* Optiland: ``FFTPSF(num_rays=128, grid_size=256)`` (its optic built once, outside the timing).

Printed: the best of ``--repeat`` timings of each, their ratio (Optiland / ours: > 1 means we are
faster), and for scale the time of one full source position (nine lenslets, all bands), then the
per-position times of a scan: ``--positions`` positions drawn (seeded) from the 9×9×11 calibration
grid at 2× binning, wall and CPU seconds (CPU: this process, all threads; what the scan's workers
spend, less sensitive to other jobs on the machine), with the 1-minute load average. Needs
``pip install optiland`` (a test dependency).

    .venv/bin/python benchmarks/bench_psf.py
"""

from __future__ import annotations

import argparse
import os
import platform
import time
import warnings

from cm2optics.design import load_preset
from cm2optics.emission.analysis import central_lenslet
from cm2optics.emission.crosscheck import optiland_lenslet
from cm2optics.emission.psf import EmissionModel, PSFSettings
from cm2optics.emission.source import calibration_pinhole
from cm2optics.optics.backend import variant


def best_of(repeat: int, call) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20, help="timed runs of each (the best is kept)")
    parser.add_argument("--field-mm", type=float, default=0.0, help="source height in the focal plane, mm")
    parser.add_argument("--positions", type=int, default=40, help="scan positions timed at 2x binning (0: none)")
    args = parser.parse_args()

    from optiland.psf import FFTPSF

    design = load_preset("cm2-v2")
    model = EmissionModel(design, calibration_pinhole(), settings=PSFSettings(binning=1))
    k = central_lenslet(model)
    band = model._mid_band
    wavelength_nm = float(model.bands.wavelength_nm[band])
    position = (0.0, args.field_mm, 0.0)
    optic = optiland_lenslet(design, wavelength_nm, args.field_mm)
    field = (0.0, 1.0 if args.field_mm > 0 else 0.0)

    def ours() -> None:
        model.foci(position, lenslets=[k], bands=[band])

    def theirs() -> None:
        FFTPSF(optic, field, wavelength_nm / 1000.0, num_rays=128, grid_size=256)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ours()
        theirs()  # warm-up: kernels compiled, caches filled
        t_ours = best_of(args.repeat, ours)
        t_theirs = best_of(args.repeat, theirs)
        t_position = best_of(max(3, args.repeat // 5), lambda: model.foci(position))

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; Mitsuba variant {variant().variant}"
    )
    print(f"case: central lenslet of {design.name}, source at {position} mm, {wavelength_nm:.1f} nm")
    print(f"ours     (one lenslet, one band, pixel-integrated): {t_ours * 1000:8.2f} ms")
    print(f"Optiland (FFTPSF, 128 rays, 256 grid):               {t_theirs * 1000:8.2f} ms")
    print(f"ratio Optiland / ours: {t_theirs / t_ours:.2f}  (> 1: ours is faster)")
    print(
        f"one full source position (9 lenslets x {len(model.bands)} bands, {design.sensor.pixel_um:g}-um pixels): {t_position * 1000:.0f} ms"
    )
    if args.positions > 0:
        scan_positions(design, args.positions)


def scan_positions(design, count: int, seed: int = 0) -> None:
    """Wall and CPU time per position of the 9×9×11 calibration grid at 2× binning."""
    import numpy as np

    from cm2optics.emission.scan import ScanSettings, calibration_grid_mm

    settings = ScanSettings(psf=PSFSettings(binning=2))
    model = EmissionModel(design, settings.source, settings=settings.psf)
    grid = calibration_grid_mm(design, (9, 9, 11))
    model.foci(grid[0])  # warm-up
    pick = np.random.default_rng(seed).choice(len(grid), min(count, len(grid)), replace=False)
    wall, cpu = [], []
    for i in pick:
        w0, c0 = time.perf_counter(), time.process_time()
        model.foci(grid[i])
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    wall, cpu = np.array(wall), np.array(cpu)
    print(
        f"scan positions (9x9x11 grid, 2x binning, {len(pick)} drawn): wall mean {wall.mean():.3f} s, median "
        f"{np.median(wall):.3f} s, max {wall.max():.3f} s; CPU mean {cpu.mean():.3f} s, max {cpu.max():.3f} s; "
        f"load {os.getloadavg()[0]:.1f}"
    )
    print(
        f"  -> a 891-position scan on {os.cpu_count()} workers: about {891 * cpu.mean() / (os.cpu_count() or 1):.0f} s of computing on free cores"
    )


if __name__ == "__main__":
    main()
