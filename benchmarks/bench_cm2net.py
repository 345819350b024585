"""Time CM²Net's full-field inference on the CPU against FISTA on the same field, in the same run.

Project: one forward pass of the network (``--config``, default the CPU config; ``--channels`` /
``--blocks`` override its width and depth) on the nine ``--size``-px views of a measurement (the
config's views by default), as :func:`cm2optics.recon.net.infer.reconstruct_with_net` runs it:
fp32, then each variant on its own — channels-last memory format, bf16 autocast — with its
ratio to fp32. The weights are freshly initialised (timing and memory do not depend on them).

Reference: FISTA (:func:`cm2optics.recon.solvers.fista`) with the config's 3D-LSV model on the
same field and planes: one iteration timed (best of ``--repeat``) × ``--iterations``.

Peak memory is the process's resident-set high-water mark over each measurement (reset through
``/proc/self/clear_refs``; on systems without it, the sampled peak), less the resident set before,
after glibc's ``malloc_trim`` has returned freed memory (else reused pages would hide the peak).

Usage::

    python benchmarks/bench_cm2net.py --size 128            # a quick run
    python benchmarks/bench_cm2net.py                       # the CPU config's 512-px views
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
    best, peak = float("inf"), 0
    for _ in range(repeat):
        with PeakMemory() as memory:
            start = time.perf_counter()
            function()
            elapsed = time.perf_counter() - start
        best = min(best, elapsed)
        peak = max(peak, memory.bytes)
    return best, peak


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=REPO / "reconstruction" / "configs" / "cm2net-cpu.yaml")
    parser.add_argument("--size", type=int, default=None, help="side of the views, px (default: the config's view_px)")
    parser.add_argument("--channels", type=int, default=None, help="network width (default: the config's)")
    parser.add_argument(
        "--blocks", type=int, default=None, help="residual blocks per sub-network (default: the config's)"
    )
    parser.add_argument(
        "--planes",
        type=int,
        default=None,
        help="output planes (default: the config's); needs a forward model that fits",
    )
    parser.add_argument("--iterations", type=int, default=100, help="FISTA iterations the reference stands for")
    parser.add_argument("--repeat", type=int, default=2, help="timed runs of each figure (best kept)")
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--skip-fista", action="store_true")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from cm2optics.recon.net._compat import VolumeGrid

    from cm2optics.recon.net.config import load_config
    from cm2optics.recon.net.data import forward_imaging
    from cm2optics.recon.net.train import make_net

    config = load_config(args.config)
    changes = {k: v for k, v in (("channels", args.channels), ("blocks", args.blocks)) if v is not None}
    config = config.with_changes(**changes) if changes else config
    size = args.size or config.synth.view_px
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
    }
    print(
        f"CM²Net {config.channels} ch × {config.blocks} blocks, {net.planes.n_planes} → {config.n_planes} planes, "
        f"{net.parameter_count():,} parameters; views 9 × {size}², {args.threads} threads"
    )

    def run(model, x, autocast=False):
        def go():
            with (
                torch.inference_mode(),
                torch.autocast("cpu", dtype=torch.bfloat16) if autocast else contextlib.nullcontext(),
            ):
                model(x)

        return go

    run(net, views)()  # warm-up
    t_fp32, m_fp32 = best_of(args.repeat, run(net, views))
    results["net_fp32"] = {"seconds": t_fp32, "peak_mib": m_fp32 / 2**20}
    print(f"  fp32                 {t_fp32:8.3f} s   peak {m_fp32 / 2**20:8.1f} MiB")

    net_cl = net.to(memory_format=torch.channels_last)
    views_cl = views.contiguous(memory_format=torch.channels_last)
    run(net_cl, views_cl)()
    t_cl, m_cl = best_of(args.repeat, run(net_cl, views_cl))
    results["net_channels_last"] = {"seconds": t_cl, "peak_mib": m_cl / 2**20, "time_ratio_vs_fp32": t_cl / t_fp32}
    print(f"  channels-last        {t_cl:8.3f} s   peak {m_cl / 2**20:8.1f} MiB   time ×{t_cl / t_fp32:.2f} of fp32")
    net = net.to(memory_format=torch.contiguous_format)

    run(net, views, autocast=True)()
    t_bf, m_bf = best_of(args.repeat, run(net, views, autocast=True))
    results["net_bf16_autocast"] = {"seconds": t_bf, "peak_mib": m_bf / 2**20, "time_ratio_vs_fp32": t_bf / t_fp32}
    print(f"  bf16 autocast        {t_bf:8.3f} s   peak {m_bf / 2**20:8.1f} MiB   time ×{t_bf / t_fp32:.2f} of fp32")
    with torch.inference_mode():
        a = torch.sigmoid(net(views)[1])
        with torch.autocast("cpu", dtype=torch.bfloat16):
            b = torch.sigmoid(net(views)[1].float())
    results["bf16_max_abs_diff"] = float((a - b).abs().max())
    print(f"  bf16 vs fp32 output: max |Δσ| = {results['bf16_max_abs_diff']:.3g}")

    if not args.skip_fista:
        from cm2optics.recon.solvers import Stopping, fista, lipschitz

        imaging = forward_imaging(config)
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
            L = lipschitz(operator)
            stopping = Stopping(max_iter=1, tol=0.0)
            fista(operator, measurement, l1=0.01, stopping=stopping, lipschitz_value=L)  # warm-up
            t_it, m_it = best_of(
                args.repeat, lambda: fista(operator, measurement, l1=0.01, stopping=stopping, lipschitz_value=L)
            )
            total = t_it * args.iterations
            results["fista"] = {
                "seconds_per_iteration": t_it,
                "iterations": args.iterations,
                "seconds": total,
                "peak_mib": m_it / 2**20,
            }
            results["speedup_net_vs_fista"] = total / t_fp32
            print(
                f"  FISTA, one iteration {t_it:8.3f} s   peak {m_it / 2**20:8.1f} MiB   × {args.iterations} = {total:.1f} s"
            )
            print(
                f"  CM²Net fp32 is {total / t_fp32:.1f}× faster than {args.iterations} FISTA iterations on this field"
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
