"""Time CM²Net's full-field inference on the CPU against FISTA on the same field, in the same run.

Project: one forward pass of the network (``--config``, default the CPU config; ``--channels`` /
``--blocks`` override its width and depth) on the nine ``--size``-px views of a measurement (the
config's views by default), as :func:`cm2optics.recon.net.infer.reconstruct_with_net` runs it:
fp32, then each variant on its own — channels-last memory format, batch norms folded into the
convolutions with channels-last (what the inference runs), bf16 autocast, torch.compile — with
its ratio to fp32. The weights are freshly initialised (timing and memory do not depend on them;
the batch norms' running statistics are the initial ones, folding costs the same either way).

Reference: FISTA (:func:`cm2optics.recon.solvers.fista`) with the config's 3D-LSV model on the
same field and planes: one iteration timed (best of ``--repeat``, after one warm-up; the step
size is not computed, it does not change an iteration's cost) × ``--iterations``.

Each figure also gives the CPU time of all threads (``time.process_time``), so that a run on a
loaded machine can be read per core, and the load average at the start and end.

The full inference also resamples the planes onto the object grid with a lateral correction
(:mod:`cm2optics.recon.net.lateral`; a representative one, timing does not depend on it) and may
detect emitters: both timed on their own.

Peak memory is the process's resident-set high-water mark over each measurement (reset through
``/proc/self/clear_refs``; on systems without it, the sampled peak), less the resident set before,
after glibc's ``malloc_trim`` has returned freed memory (else reused pages would hide the peak).

Usage::

    python benchmarks/bench_cm2net.py --size 128            # a quick run
    python benchmarks/bench_cm2net.py                       # the CPU config's 512-px views
    python benchmarks/bench_cm2net.py --size 1920 --planes 80   # issue 15's full field, CPU network
    python benchmarks/bench_cm2net.py --config reconstruction/configs/cm2net-full.yaml --size 1920
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]


def _status(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    return 0


def _trim() -> None:
    """Give freed heap memory back to the system, so that the next peak counts fresh pages."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)


class PeakMemory:
    """Peak resident set (bytes) above the level at entry (freed heap memory trimmed first)."""

    def __enter__(self):
        _trim()
        self.base = _status("VmRSS:")
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # resets VmHWM to the current RSS
            self.hwm = True
        except OSError:
            self.hwm = False
        self.peak = self.base
        self._stop = threading.Event()
        if not self.hwm:
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _sample(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, _status("VmRSS:"))
            time.sleep(0.002)

    def __exit__(self, *exc):
        self._stop.set()
        if self.hwm:
            self.peak = _status("VmHWM:")
        else:
            self._thread.join()
        self.bytes = max(self.peak - self.base, 0)
        return False


def best_of(repeat: int, function):
    """Best wall time of ``repeat`` runs, the CPU time (all threads) of that run, and the peak
    resident memory above the start (bytes) over all runs."""
    best, cpu, peak = float("inf"), 0.0, 0
    for _ in range(repeat):
        with PeakMemory() as memory:
            start, start_cpu = time.perf_counter(), time.process_time()
            function()
            elapsed, used = time.perf_counter() - start, time.process_time() - start_cpu
        if elapsed < best:
            best, cpu = elapsed, used
        peak = max(peak, memory.bytes)
    return best, cpu, peak


def _config(args):
    """The config with the command line's width, depth and planes (``--planes P``: the depth
    range grows to (P − 1) planes of the config's dz) and views as large as ``--size``."""
    from cm2optics.recon.net.config import load_config

    config = load_config(args.config)
    changes = {k: v for k, v in (("channels", args.channels), ("blocks", args.blocks)) if v is not None}
    synth = config.synth
    if args.planes is not None:
        changes["n_planes"] = args.planes
        synth = synth.with_changes(depth_um=(args.planes - 1) * synth.voxel_um[0])
    size = args.size or synth.view_px
    changes["synth"] = synth.with_changes(view_px=size, patch_px=min(synth.patch_px, size))
    return config.with_changes(**changes), size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=REPO / "reconstruction" / "configs" / "cm2net-cpu.yaml")
    parser.add_argument("--size", type=int, default=None, help="side of the views, px (default: the config's view_px)")
    parser.add_argument("--channels", type=int, default=None, help="network width (default: the config's)")
    parser.add_argument(
        "--blocks", type=int, default=None, help="residual blocks per sub-network (default: the config's)"
    )
    parser.add_argument("--planes", type=int, default=None, help="output planes (default: the config's)")
    parser.add_argument("--iterations", type=int, default=100, help="FISTA iterations the reference stands for")
    parser.add_argument("--repeat", type=int, default=2, help="timed runs of each figure (best kept)")
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--skip-fista", action="store_true")
    parser.add_argument("--skip-compile", action="store_true", help="leave out torch.compile")
    parser.add_argument("--no-warmup", action="store_true", help="no untimed pass before each (large fields)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from cm2optics.formats.volume import VolumeGrid
    from cm2optics.metrics import detect_emitters
    from cm2optics.recon.net.data import forward_imaging, pixel_voxel_um
    from cm2optics.recon.net.lateral import LateralCorrection, volume_on_grid
    from cm2optics.recon.net.model import fused_for_inference
    from cm2optics.recon.net.train import make_net

    config, size = _config(args)
    net, _ = make_net(config)
    net.eval()
    views = torch.rand(1, net.n_views, size, size) * 0.2
    results: dict = {
        "config": str(args.config),
        "channels": config.channels,
        "blocks": config.blocks,
        "planes": config.n_planes,
        "refocus_planes": net.planes.n_planes,
        "size_px": size,
        "parameters": net.parameter_count(),
        "threads": args.threads,
        "torch": torch.__version__,
        "load_average_at_start": os.getloadavg(),
    }
    print(
        f"CM²Net {config.channels} ch × {config.blocks} blocks, {net.planes.n_planes} → {config.n_planes} planes, "
        f"{net.parameter_count():,} parameters; views 9 × {size}², {args.threads} threads; "
        f"load {os.getloadavg()[0]:.1f}"
    )

    outputs: dict = {}

    def run(model, x, autocast=False, keep=None):
        def go():
            with (
                torch.inference_mode(),
                torch.autocast("cpu", dtype=torch.bfloat16) if autocast else contextlib.nullcontext(),
            ):
                volume = torch.sigmoid(model(x)[1].float())
            if keep:
                outputs[keep] = volume

        return go

    def warm(go):
        if not args.no_warmup:
            go()

    def record(name, seconds, cpu, peak, **extra):
        results[name] = {"seconds": seconds, "cpu_seconds": cpu, "peak_gib": peak / 2**30, **extra}
        ratio = f"   time ×{seconds / results['net_fp32']['seconds']:.2f} of fp32" if "net_fp32" in results else ""
        print(f"  {name:22s} {seconds:8.2f} s  (CPU {cpu:7.1f} s)  peak {peak / 2**30:6.2f} GiB{ratio}")

    warm(run(net, views))
    record("net_fp32", *best_of(args.repeat, run(net, views, keep="fp32")))

    net_cl = net.to(memory_format=torch.channels_last)
    views_cl = views.contiguous(memory_format=torch.channels_last)
    warm(run(net_cl, views_cl))
    record("net_channels_last", *best_of(args.repeat, run(net_cl, views_cl)))
    net = net.to(memory_format=torch.contiguous_format)

    # what the inference runs: batch norms folded into the convolutions, channels-last
    fused = fused_for_inference(net).to(memory_format=torch.channels_last)
    warm(run(fused, views_cl))
    record("net_fused_bn_channels_last", *best_of(args.repeat, run(fused, views_cl, keep="fused")))
    results["fused_max_abs_diff"] = float((outputs["fp32"] - outputs.pop("fused")).abs().max())
    print(f"  fused vs fp32 output: max |Δσ| = {results['fused_max_abs_diff']:.3g}")
    del fused

    warm(run(net, views, autocast=True))
    record("net_bf16_autocast", *best_of(args.repeat, run(net, views, autocast=True, keep="bf16")))
    results["bf16_max_abs_diff"] = float((outputs["fp32"] - outputs.pop("bf16")).abs().max())
    print(f"  bf16 vs fp32 output: max |Δσ| = {results['bf16_max_abs_diff']:.3g}")

    if not args.skip_compile:
        try:
            start = time.perf_counter()
            compiled = torch.compile(net)
            run(compiled, views)()  # compiles
            results["compile_seconds"] = time.perf_counter() - start
            record("net_torch_compile", *best_of(args.repeat, run(compiled, views)))
        except Exception as error:  # noqa: BLE001 - a lever that does not work here is a result too
            results["net_torch_compile"] = {"error": f"{type(error).__name__}: {str(error)[:200]}"}
            print(f"  torch.compile failed: {results['net_torch_compile']['error']}")

    # the rest of the inference: planes resampled onto the object grid (lateral correction), detection
    raw = outputs.pop("fp32")[0].numpy()
    imaging = forward_imaging(config)
    scale = np.asarray(imaging.pixels_per_voxel(), float)
    voxel = pixel_voxel_um(config, scale)
    correction = LateralCorrection((0.0, 0.07, 0.0), ((0.0, -24.0, -200.0), (0.0, 0.0, -80.0)))
    z_mm = net.volume_z_mm.numpy()
    record("resample_to_grid", *best_of(args.repeat, lambda: volume_on_grid(raw, z_mm, voxel[1:], scale, correction)))
    volume = volume_on_grid(raw, z_mm, voxel[1:], scale, correction)
    grid = VolumeGrid(volume.shape, voxel)
    record("detect_emitters", *best_of(1, lambda: detect_emitters(volume, grid, 0.5)))

    if not args.skip_fista:
        from cm2optics.recon.solvers import Stopping, fista

        model = imaging.source
        if not hasattr(model, "operator"):
            print("  (the config's forward model has no LSV operator: FISTA skipped)")
        else:
            grid = VolumeGrid((config.n_planes, size, size), config.synth.grid.voxel_um)
            operator = model.operator(grid)
            volume = np.zeros(grid.shape, np.float32)
            rng = np.random.default_rng(0)
            volume[rng.integers(0, grid.shape[0], 50), rng.integers(0, size, 50), rng.integers(0, size, 50)] = 1.0
            measurement = operator.forward(volume)
            L = 1.0  # the step size does not change an iteration's cost (the power iterations would)
            stopping = Stopping(max_iter=1, tol=0.0)
            fista(operator, measurement, l1=0.01, stopping=stopping, lipschitz_value=L)  # warm-up
            t_it, cpu_it, m_it = best_of(
                args.repeat, lambda: fista(operator, measurement, l1=0.01, stopping=stopping, lipschitz_value=L)
            )
            total = t_it * args.iterations
            results["fista"] = {
                "seconds_per_iteration": t_it,
                "cpu_seconds_per_iteration": cpu_it,
                "iterations": args.iterations,
                "seconds": total,
                "peak_gib": m_it / 2**30,
            }
            # what `cm2 reconstruct --method net` runs (cm2optics.recon.net.infer): the fused,
            # channels-last network, then the resampling onto the object grid
            resample = results["resample_to_grid"]["seconds"]
            pipeline = results["net_fused_bn_channels_last"]["seconds"] + resample
            plain = results["net_fp32"]["seconds"] + resample
            results["inference_seconds"] = pipeline
            results["speedup_net_vs_fista"] = total / pipeline
            results["speedup_fp32_net_vs_fista"] = total / plain
            print(
                f"  FISTA, one iteration {t_it:8.2f} s  (CPU {cpu_it:7.1f} s)  peak {m_it / 2**30:6.2f} GiB   "
                f"× {args.iterations} = {total:.1f} s (extrapolated from one iteration)"
            )
            print(
                f"  CM²Net as inference runs it (fused + channels-last + resampling, {pipeline:.1f} s) is "
                f"{total / pipeline:.1f}× faster than {args.iterations} FISTA iterations "
                f"(plain fp32 + resampling: {total / plain:.1f}×)"
            )
    results["load_average_at_end"] = os.getloadavg()
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
