"""Time one full-size synthetic training volume + measurement against the naive way, in the same run.

Project: :func:`cm2optics.synth.generate.synthesize_sample` at the paper's size (field 7.5 mm, the
densest draw 100 emitters/mm² unless --density says otherwise, the model's 4.13 × 4.13 × 10 µm
voxels, ≈ 81 × 1815 × 1815 grid, balls on a 5× finer grid averaged down, the measurement from the
3D-LSV model with its sparse emitter renderer, noise): the training volume + measurement. Then,
once, the whole training sample (each lenslet rendered on its own for the demixed ground truth,
the nine 1920 × 1920 views).

Reference, same emitters: the volume rasterised one emitter at a time on an explicit fine grid
(:func:`cm2optics.synth.raster.rasterize_balls_naive`), and the measurement as the forward of the
volume through the LSV operator (``--reference-forward``, minutes and several GiB at full size).

Each figure is the best of ``--repeat`` runs (the machine is shared). Usage::

    python benchmarks/bench_synth.py --model out/lsv-full.h5 [--repeat 3] [--reference-forward]

Without ``--model`` a full-resolution analytic model is built once into ``--cache`` (≈ 6 min).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from cm2optics.synth.config import SynthConfig
from cm2optics.synth.emitters import sample_emitters, sample_rng
from cm2optics.synth.generate import synthesize_sample
from cm2optics.synth.imaging import Imaging
from cm2optics.synth.raster import rasterize_balls, rasterize_balls_naive


def build_full_model(cache: Path) -> Path:
    from cm2optics.design import load_preset
    from cm2optics.lsv.build import build_model
    from cm2optics.lsv.toy import AnalyticCM2, write_analytic_scan

    path = cache / "lsv-full.h5"
    if path.is_file():
        return path
    design = load_preset("cm2-v2")
    xs = np.linspace(-3.6, 3.6, 7)
    write_analytic_scan(cache / "scan-full", AnalyticCM2.from_design(design), xs, xs, np.linspace(-0.4, 0.4, 3))
    return build_model(cache / "scan-full", rank=8, design=design).model.save(path)


def best_of(repeat: int, function):
    """(best seconds, the result of that best run)."""
    best, best_result = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        result = function()
        elapsed = time.perf_counter() - start
        if elapsed < best:
            best, best_result = elapsed, result
        del result
    return best, best_result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, help="full-resolution LSV model (HDF5)")
    parser.add_argument("--cache", type=Path, default=Path("out/bench"), help="where to build a model if none is given")
    parser.add_argument("--density", type=float, default=100.0, help="emitters per mm² (paper: 10–100)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--reference-forward", action="store_true", help="also time the dense LSV forward of the volume"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    from cm2optics.lsv.model import load_model

    args.cache.mkdir(parents=True, exist_ok=True)
    model = load_model(args.model or build_full_model(args.cache))
    config = SynthConfig.paper().with_changes(
        fov_mm=(7.5, 7.5),
        density_per_mm2=(args.density, args.density),
        patch_px=0,
        voxel_um=model.default_grid.voxel_um,
    )
    grid = config.grid
    imaging = Imaging(model, grid, "sparse")
    draw = sample_emitters(config, sample_rng(0, 0))
    n = len(draw.emitters)
    print(
        f"model: sensor {model.sensor_shape}, rank {model.rank}; grid {grid.shape} ({np.prod(grid.shape) / 1e6:.0f} M voxels) "
        f"of {grid.voxel_um[1]:.3f} × {grid.voxel_um[2]:.3f} × {grid.voxel_um[0]:g} µm; {n} emitters"
    )
    measure = config.with_changes(view_px=0)
    synthesize_sample(measure, imaging, 0, 0)  # warm-up (imports, FFT plans, page faults)
    total, sample = best_of(args.repeat, lambda: synthesize_sample(measure, imaging, 0, 0))
    parts = sample.seconds
    print(
        f"project: volume + noisy measurement = {total:.2f} s  (emitters {parts['emitters']:.2f} s, volume {parts['volume']:.2f} s, "
        f"measurement {parts['imaging']:.2f} s, noise {parts['noise']:.2f} s)"
    )
    full_s, full = best_of(1, lambda: synthesize_sample(config, imaging, 0, 0))
    print(
        f"with the nine demixed ground-truth views (each lenslet rendered on its own) and the 1920-px views: {full_s:.2f} s "
        f"(imaging {full.seconds['imaging']:.2f} s)"
    )
    del full
    fast_volume, volume = best_of(args.repeat, lambda: rasterize_balls(draw.emitters, grid))
    naive_volume, reference = best_of(1, lambda: rasterize_balls_naive(draw.emitters, grid))
    agree = float(np.abs(volume - reference).max())
    print(
        f"volume: vectorised {fast_volume:.2f} s, naive per-emitter {naive_volume:.2f} s → ratio {naive_volume / fast_volume:.1f}× "
        f"(max |difference| {agree:.1e})"
    )
    result = {
        "emitters": n,
        "grid": list(grid.shape),
        "project_s": round(total, 3),
        "parts_s": {k: round(v, 3) for k, v in parts.items()},
        "with_demixed_views_s": round(full_s, 3),
        "volume_vectorised_s": round(fast_volume, 3),
        "volume_naive_s": round(naive_volume, 3),
        "volume_ratio": round(naive_volume / fast_volume, 2),
    }
    if args.reference_forward:
        del reference
        operator = model.operator(grid)
        dense_s, image = best_of(1, lambda: operator.forward(volume))
        sparse_s, _ = best_of(args.repeat, lambda: model.forward_sparse(draw.emitters))
        print(
            f"measurement: sparse renderer {sparse_s:.2f} s, dense LSV forward of the volume {dense_s:.2f} s → ratio {dense_s / sparse_s:.1f}×"
        )
        result |= {"measurement_sparse_s": round(sparse_s, 3), "measurement_dense_s": round(dense_s, 3)}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
