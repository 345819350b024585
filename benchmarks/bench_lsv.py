"""Benchmark: the 3D-LSV forward model against the naive per-(k, z) scipy FFT convolution.

The model is a full-size synthetic CM² V2 model (3088 × 2076 sensor, 9 × 9 × 11 calibration
nodes, K = 64, foci cropped at 160 × 160 px; ``--no-trim`` keeps the full crops, by default their
dark margins are cut as ``cm2 lsv build`` does) of the analytic CM²-like PSF
(:mod:`cm2optics.lsv.toy`). The volume is a dense random 1920 × 1920 × 80 volume at the
model's native voxel (4.15 × 4.15 × 10 µm).

- **Ours**: :class:`cm2optics.lsv.operators.LSVOperator` forward (torch, float32), timed
  ``--repeat`` times; peak resident memory of the process during the call.
- **Reference**: :func:`cm2optics.lsv.reference.reference_forward`, the model's definition
  evaluated naively — for every (k, z) one scipy ``fftconvolve`` per lenslet (float64), with the
  coefficient maps interpolated pixel by pixel. A full run is K·nz = 5,120 (k, z) pairs (hours on
  this machine), so by default it is timed on one depth plane: the per-plane set-up
  (splat, shifts, coefficient maps) and the per-(k, z) convolutions separately, then
  extrapolated linearly to all pairs (the cost of a pair does not depend on k or z);
  ``--full-reference`` runs it all.
- **Accuracy**: both on the same full-size problem restricted to ``--check-planes`` planes and
  ``--check-ranks`` basis PSFs (the rest zero), so that the reference can run every pair: the
  relative error ‖ours − reference‖ / ‖reference‖ (the issue asks ≤ 1e-4).
- **Cross-coupling** (``--cross-coupling-px X``): the model's stage and sensor axes coupled so
  that a point at the edge of the calibrated field moves X px across (a real fit leaves
  ≈ 0.1 px): the operator's 'general' path (bilinear splat through the full 2×2 map, lateral
  weights in the stage's x and y, both evaluated on the fly). ``--adjoint`` times an adjoint too;
  the peak resident memory of the whole run (``getrusage``) is printed at the end.
- **Sparse**: 5,000 emitters (balls of 10–20 µm in a 7-mm disc, ±0.4 mm deep) through the sparse
  path (:mod:`cm2optics.lsv.sparse`).

Absolute times are noisy on a shared machine: each figure is the best of its repeats, all
repeats are printed, and the load average is shown.

    .venv/bin/python benchmarks/bench_lsv.py            # full size (≈ 5 min)
    .venv/bin/python benchmarks/bench_lsv.py --small    # binned 4×, 20 planes (≈ 1 min)
    .venv/bin/python benchmarks/bench_lsv.py --cross-coupling-px 0.13 --adjoint --repeat 1

**ePSF models** (``--epsf-model MODEL.h5``, a model built with ``--oversample S``; only this part
runs): the same volume through the ePSF operator at every sampling S' of ``--epsf-samplings``
(:class:`cm2optics.lsv.epsf.EPSFOperator`: the whole-pixel operator on a grid S' times finer;
S' = 1 is the whole-pixel operator of the same model, the ePSF taken at the pixel centres, and
the largest S' = S the exact reference): forward and adjoint wall and CPU seconds, the peak
resident memory a call adds, the operator's own memory, the ratios to S' = 1, and each
sampling's relative error against S' = S on a dense random volume and on sparse voxels. Then why
a cheaper exact operator is hard to get (see BENCHMARKS.md): per lenslet, the rank of the joint
(basis, sub-pixel phase) set of whole-pixel kernels and the node PSFs' energy beyond the pixel
Nyquist frequency.

    .venv/bin/python benchmarks/bench_lsv.py --epsf-model out/lsv/model.h5 --epsf-grid 20,400
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import threading
import time
from pathlib import Path

import numpy as np
import torch

from cm2optics.design import load_preset
from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.model import LSVModel
from cm2optics.lsv.reference import reference_forward
from cm2optics.lsv.toy import AnalyticCM2, analytic_lsv_model


class PeakMemory:
    """Peak resident set size (bytes) of this process while the block runs (sampled every 20 ms,
    after resetting the kernel's high-water mark where Linux allows it)."""

    def __enter__(self) -> PeakMemory:
        self.peak = 0
        self._stop = threading.Event()
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            pass
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _rss(self) -> int:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(("VmRSS", "VmHWM")):
                self.peak = max(self.peak, int(line.split()[1]) * 1024)
        return self.peak

    def _sample(self) -> None:
        while not self._stop.is_set():
            self._rss()
            time.sleep(0.02)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._rss()


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "n/a"


def restricted(model: LSVModel, ranks: int) -> LSVModel:
    """The same model with every coefficient beyond the first ``ranks`` basis PSFs set to zero."""
    from dataclasses import replace

    coefficients = model.coefficients.copy()
    coefficients[ranks:] = 0
    return replace(model, coefficients=coefficients)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", action="store_true", help="binned 4× sensor, 480 × 480 × 20 volume: a quick run")
    parser.add_argument("--rank", type=int, default=64)
    parser.add_argument(
        "--per-lenslet-basis", action="store_true", help="each lenslet its own K-term basis (J·K terms in all)"
    )
    parser.add_argument("--no-trim", action="store_true", help="keep the full 160-px crops (no dark-margin trimming)")
    parser.add_argument("--repeat", type=int, default=2, help="timed runs of ours (best kept)")
    parser.add_argument(
        "--reference-ranks", type=int, default=3, help="(k, z) pairs of one plane timed for the reference"
    )
    parser.add_argument("--full-reference", action="store_true", help="run the reference on every (k, z) pair (hours)")
    parser.add_argument("--check-planes", type=int, default=2)
    parser.add_argument("--check-ranks", type=int, default=2)
    parser.add_argument("--emitters", type=int, default=5000)
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument(
        "--cross-coupling-px", type=float, default=0.0, help="stage/sensor cross-coupling at the field's edge, px"
    )
    parser.add_argument("--adjoint", action="store_true", help="also time one adjoint")
    parser.add_argument("--skip-reference", action="store_true", help="skip the reference timing and accuracy check")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--epsf-model", type=Path, help="an ePSF model file: compare its operator's samplings only")
    parser.add_argument("--epsf-grid", default="20,400", help="ePSF volume: planes,lateral voxels (native pitch)")
    parser.add_argument("--epsf-samplings", default="1,2,4", help="ePSF samplings S' to compare (divisors of S)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.epsf_model:
        finish(epsf_comparison(args), args)
        return
    binning, nz, n_lateral = (4, 20, 480) if args.small else (1, 80, 1920)
    results: dict[str, object] = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch threads {args.threads}",
        "load_at_start": load(),
        "small": args.small,
    }

    basis = "per lenslet" if args.per_lenslet_basis else "focus arrays"
    print(f"building the synthetic model (binning {binning}, K = {args.rank}, basis: {basis}) …", flush=True)
    start = time.perf_counter()
    design = load_preset("cm2-v2")
    analytic = AnalyticCM2.from_design(design, binning=binning, sigma0_um=design.sensor.pixel_um * binning)
    axis = np.linspace(-4, 4, 9)
    model = analytic_lsv_model(
        analytic,
        axis,
        axis,
        np.linspace(-0.5, 0.5, 11),
        rank=args.rank,
        trim=None if args.no_trim else 1e-6,
        per_lenslet=args.per_lenslet_basis,
    )
    if args.cross_coupling_px:
        model = cross_coupled(model, args.cross_coupling_px)
    native = model.default_grid.voxel_um[1]
    grid = VolumeGrid((nz, n_lateral, n_lateral), (design.volume.axial_step_um, native, native))
    results["model"] = {
        "sensor": list(model.sensor_shape),
        "rank": model.rank,
        "basis": basis,
        "patch_px": list(model.patch_shape),
        "crop_px": model.provenance["svd"]["crop_px"],
        "nmse_calibration": model.provenance["svd"]["nmse_model"],  # the saved model's (the SVD's: svd.nmse)
        "seconds": round(time.perf_counter() - start, 1),
    }
    results["grid"] = grid.to_dict()
    print(
        f"  sensor {model.sensor_shape}, patch {model.patch_shape} (crops {model.provenance['svd']['crop_px']}), "
        f"volume {grid.shape} × {tuple(round(v, 3) for v in grid.voxel_um)} µm",
        flush=True,
    )

    rng = np.random.default_rng(0)
    volume = torch.rand(grid.shape, generator=torch.Generator().manual_seed(0))
    start = time.perf_counter()
    op = model.operator(grid)
    results["operator"] = {
        "path": op._kind_all,
        "set_up_s": round(time.perf_counter() - start, 2),
        "kept_gib": op.memory_bytes() / 2**30,
        "transient_gib": op.transient_bytes() / 2**30,
    }
    print(
        f"operator: {op._kind_all} path, set up in {results['operator']['set_up_s']} s, keeps "
        f"{results['operator']['kept_gib']:.3f} GiB, ≤ {results['operator']['transient_gib']:.2f} GiB per call",
        flush=True,
    )

    # ours: dense forward
    times = []
    peak = 0
    for _ in range(args.repeat):
        with PeakMemory() as memory:
            start = time.perf_counter()
            image = op.forward(volume)
            times.append(time.perf_counter() - start)
        peak = max(peak, memory.peak)
    results["ours"] = {
        "seconds_best": min(times),
        "seconds_all": times,
        "peak_rss_gib": peak / 2**30,
        "volume_gib": volume.numel() * 4 / 2**30,
        "load": load(),
    }
    print(
        f"ours: forward {min(times):.1f} s (all {[round(t, 1) for t in times]}), peak RSS {peak / 2**30:.2f} GiB "
        f"(the volume alone {volume.numel() * 4 / 2**30:.2f} GiB), load {load()}",
        flush=True,
    )
    del image
    if args.adjoint:
        y = torch.rand(model.sensor_shape, generator=torch.Generator().manual_seed(1))
        with PeakMemory() as memory:
            start = time.perf_counter()
            op.adjoint(y)
            adjoint_s = time.perf_counter() - start
        results["adjoint"] = {"seconds": adjoint_s, "peak_rss_gib": memory.peak / 2**30, "load": load()}
        print(f"ours: adjoint {adjoint_s:.1f} s, peak RSS {memory.peak / 2**30:.2f} GiB, load {load()}", flush=True)
    if args.skip_reference:
        finish(results, args)
        return

    # reference: time one plane's set-up and its per-(k, z) convolutions, extrapolate
    volume_np = volume.numpy()
    K = model.rank
    z0 = nz // 2
    if args.full_reference:
        start = time.perf_counter()
        reference_forward(model, op, volume_np)
        total = time.perf_counter() - start
        results["reference"] = {"seconds": total, "extrapolated": False}
    else:
        timings = {}
        for n in (1, 1 + args.reference_ranks):
            start = time.perf_counter()
            reference_forward(model, op, volume_np, pairs=[(k, z0) for k in range(n)])
            timings[n] = time.perf_counter() - start
        per_pair = (timings[1 + args.reference_ranks] - timings[1]) / args.reference_ranks
        per_plane = max(timings[1] - per_pair, 0.0)
        total = nz * per_plane + K * nz * per_pair
        results["reference"] = {
            "seconds": total,
            "extrapolated": True,
            "per_plane_setup_s": per_plane,
            "per_kz_pair_s": per_pair,
            "pairs": K * nz,
            "load": load(),
        }
        print(
            f"reference: {per_pair:.2f} s per (k, z) pair ({model.n_lenslets} fftconvolves) + {per_plane:.2f} s set-up per plane "
            f"→ {total / 60:.1f} min for all {K * nz} pairs (extrapolated), load {load()}",
            flush=True,
        )
    ratio = total / min(times)
    results["speed_ratio"] = ratio
    print(f"ratio reference / ours: {ratio:.0f}×", flush=True)

    # accuracy on a restricted problem the reference can run in full
    check = restricted(model, args.check_ranks)
    check_op = check.operator(grid)
    planes = np.linspace(1, nz - 2, args.check_planes).round().astype(int)
    sparse_volume = np.zeros(grid.shape, np.float32)
    sparse_volume[planes] = volume_np[planes]
    fast = check_op.forward(sparse_volume).astype(np.float64)
    naive = reference_forward(
        check, check_op, sparse_volume, pairs=[(k, int(z)) for z in planes for k in range(args.check_ranks)]
    )
    error = float(np.linalg.norm(fast - naive) / np.linalg.norm(naive))
    results["relative_error"] = error
    results["relative_error_problem"] = f"full size, planes {planes.tolist()}, basis PSFs 1–{args.check_ranks}"
    print(
        f"relative error ours vs reference: {error:.2e} (planes {planes.tolist()}, k < {args.check_ranks}, full size)",
        flush=True,
    )

    # sparse emitters
    n = args.emitters
    radius = 3.5 * np.sqrt(rng.random(n))
    angle = 2 * np.pi * rng.random(n)
    emitters = Emitters(
        radius * np.cos(angle) * 1000,
        radius * np.sin(angle) * 1000,
        rng.uniform(-400, 400, n),
        rng.uniform(10, 20, n),
        rng.uniform(0.5, 1.0, n),
    )
    model.forward_sparse(emitters.subset(np.arange(10)))
    sparse_times = []
    for _ in range(3):
        start = time.perf_counter()
        model.forward_sparse(emitters)
        sparse_times.append(time.perf_counter() - start)
    results["sparse"] = {"emitters": n, "seconds_best": min(sparse_times), "seconds_all": sparse_times, "load": load()}
    print(
        f"sparse: {n} emitters in {min(sparse_times):.2f} s (all {[round(t, 2) for t in sparse_times]}), load {load()}",
        flush=True,
    )

    finish(results, args)


def epsf_comparison(args: argparse.Namespace) -> dict:
    """The ePSF operator at each sampling S' on one volume (see the module docstring)."""
    from cm2optics.lsv.epsf import EPSFOperator
    from cm2optics.lsv.model import load_model

    model = load_model(args.epsf_model)
    S = model.oversample
    if S == 1:
        raise SystemExit(f"{args.epsf_model}: not an ePSF model (oversample 1)")
    samplings = sorted({int(v) for v in args.epsf_samplings.split(",")} | {S})
    planes, lateral = (int(v) for v in args.epsf_grid.split(","))
    grid = VolumeGrid((planes, lateral, lateral), model.default_grid.voxel_um)
    results: dict[str, object] = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, torch threads {args.threads}",
        "load_at_start": load(),
        "model": str(args.epsf_model),
        "oversample": S,
        "sensor": list(model.sensor_shape),
        "rank": model.rank,
        "grid": grid.to_dict(),
        "phase_structure": phase_structure(model),
    }
    print(f"ePSF model {args.epsf_model}: S = {S}, K = {model.rank}, sensor {model.sensor_shape}, volume {grid.shape}")
    for j, entry in enumerate(results["phase_structure"]):  # type: ignore[arg-type]
        print(
            f"  lenslet {j}: phase functions for residual 1e-2 / 1e-3 / 1e-4: "
            f"{' / '.join(map(str, entry['phase_rank']))} of {entry['phases']}; joint (basis, phase) rank at 1e-3 "
            f"{entry['joint_rank_1e-3']} of {entry['kernels']} (phase 0 alone {entry['phase0_rank_1e-3']}); node PSF "
            f"energy beyond Nyquist {entry['beyond_nyquist'][0]:.3f} (median), {entry['beyond_nyquist'][1]:.3f} (all)"
        )
    generator = torch.Generator().manual_seed(0)
    dense = torch.rand(grid.shape, generator=generator)
    sparse = torch.zeros(int(np.prod(grid.shape)))
    sparse[torch.randperm(sparse.numel(), generator=generator)[:200]] = 1.0
    sparse = sparse.reshape(grid.shape)
    image = torch.rand(model.sensor_shape, generator=generator)
    rows: dict[int, dict] = {}
    outputs: dict[str, torch.Tensor] = {}
    for s in samplings:
        start = time.perf_counter()
        op = EPSFOperator(model, grid, sampling=s)
        row: dict = {
            "set_up_s": time.perf_counter() - start,
            "kept_gib": op.memory_bytes() / 2**30,
            "accounted_gib": (op.memory_bytes() + op.transient_bytes()) / 2**30,  # the operator's own estimate
        }
        for name, call, data in (("forward", op.forward, dense), ("adjoint", op.adjoint, image)):
            walls, cpus, added = [], [], 0
            for _ in range(args.repeat):
                before = _rss()
                with PeakMemory() as memory:
                    wall, cpu = time.perf_counter(), time.process_time()
                    call(data)
                    walls.append(time.perf_counter() - wall)
                    cpus.append(time.process_time() - cpu)
                added = max(added, memory.peak - before)
            row[name] = {"seconds_best": min(walls), "cpu_s_best": min(cpus), "seconds_all": walls}
            row[name]["memory_gib"] = added / 2**30 + row["kept_gib"]  # the call's peak increase + the operator's
        for key, volume in (("dense", dense), ("sparse", sparse)):
            out = op.forward(volume)
            outputs[f"{key}_{s}"] = out
        row["load"] = load()
        rows[s] = row
        del op
        forward, adjoint = row["forward"], row["adjoint"]
        print(
            f"S' = {s}: set up {row['set_up_s']:.1f} s; forward {forward['seconds_best']:.1f} s "
            f"({forward['cpu_s_best']:.1f} CPU s, {forward['memory_gib']:.2f} GiB); adjoint "
            f"{adjoint['seconds_best']:.1f} s ({adjoint['cpu_s_best']:.1f} CPU s, {adjoint['memory_gib']:.2f} GiB); "
            f"operator + one call by its own account {row['accounted_gib']:.3f} GiB; load {row['load']}",
            flush=True,
        )
    for s, row in rows.items():  # against the exact path, S' = S (run last)
        for key in ("dense", "sparse"):
            exact = outputs[f"{key}_{S}"]
            row[f"error_{key}"] = float(torch.linalg.norm(outputs[f"{key}_{s}"] - exact) / torch.linalg.norm(exact))
        print(
            f"S' = {s}: relative error against S' = {S}: dense {row['error_dense']:.2e}, sparse {row['error_sparse']:.2e}"
        )
    if 1 in rows:
        for s, row in rows.items():
            for name in ("forward", "adjoint"):
                timing, whole = row[name], rows[1][name]
                timing["cpu_ratio_to_whole_pixel"] = timing["cpu_s_best"] / whole["cpu_s_best"]
                timing["memory_ratio_to_whole_pixel"] = timing["memory_gib"] / whole["memory_gib"]
            row["accounted_ratio_to_whole_pixel"] = row["accounted_gib"] / rows[1]["accounted_gib"]
            forward, adjoint = row["forward"], row["adjoint"]
            print(
                f"S' = {s} / whole pixels: forward CPU {forward['cpu_ratio_to_whole_pixel']:.2f}×, memory "
                f"{forward['memory_ratio_to_whole_pixel']:.2f}×; adjoint CPU {adjoint['cpu_ratio_to_whole_pixel']:.2f}×, "
                f"memory {adjoint['memory_ratio_to_whole_pixel']:.2f}×; by the operators' own account "
                f"{row['accounted_ratio_to_whole_pixel']:.2f}×"
            )
    results["samplings"] = {str(s): row for s, row in rows.items()}
    return results


def _rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) * 1024
    return 0


def phase_structure(model: LSVModel) -> list[dict]:
    """Per lenslet of an ePSF model, how much the whole-pixel kernel changes with the sub-pixel
    phase (each node PSF sampled at the pixel centres after a shift of (py, px)/S px, S² phases):

    - ``phase_rank``: how many phase functions φ_r(p), shared by every node, a kernel set
      ``Q_g(p) ≈ Σ_r φ_r(p)·U_gr`` needs for residual energy 1e-2, 1e-3, 1e-4 (SVD of the
      S² × (nodes·pixels) matrix): the number of image channels an operator that carries the
      phase through the depth sums would need;
    - ``joint_rank``: the rank of the K·S² kernels (every basis PSF at every phase, each basis PSF
      weighted by its coefficients' RMS over the nodes) at 1e-3, beside phase 0 alone;
    - ``beyond_nyquist``: the node PSFs' energy fraction beyond ½ cycle/px on either axis (the
      median over the nodes, and over all nodes together): what a whole-pixel kernel cannot hold."""
    S = model.oversample
    K, J, hS, wS = model.basis.shape
    h, w = hS // S, wS // S
    fy = np.abs(np.fft.fftfreq(hS, 1.0 / S))[:, None]
    fx = np.abs(np.fft.fftfreq(wS, 1.0 / S))[None, :]
    beyond = (fy >= 0.5) | (fx >= 0.5)

    def rank(gram: np.ndarray, tail: float) -> int:
        energy = np.clip(np.linalg.eigvalsh(gram)[::-1], 0.0, None)
        left = 1.0 - np.cumsum(energy) / energy.sum()
        return int(np.argmax(left < tail)) + 1

    def phases(patches: np.ndarray) -> np.ndarray:  # (n, hS, wS) → (S², n·h·w)
        return np.stack([patches[:, py::S, px::S][:, :h, :w] for py in range(S) for px in range(S)]).reshape(S * S, -1)

    out = []
    for j in range(J):
        basis = model.basis[:, j].astype(np.float64)
        flat = model.lenslet_coefficients(j).astype(np.float64).reshape(K, -1).T  # (nodes, K)
        gram = np.zeros((S * S, S * S))
        beyond_energy, energies = [], []
        for start in range(0, len(flat), 32):
            nodes = np.tensordot(flat[start : start + 32], basis, axes=(1, 0))
            samples = phases(nodes)
            gram += samples @ samples.T
            power = np.abs(np.fft.fft2(nodes)) ** 2
            energies += list(power.sum(axis=(1, 2)))
            beyond_energy += list((power * beyond).sum(axis=(1, 2)))
        energies, beyond_energy = np.array(energies), np.array(beyond_energy)
        lit = energies > 0
        weighted = basis * np.sqrt((flat**2).mean(axis=0))[:, None, None]
        kernels = phases(weighted).reshape(S * S, K, h * w)
        joint = kernels.reshape(S * S * K, h * w)
        out.append(
            {
                "phase_rank": [rank(gram, tail) for tail in (1e-2, 1e-3, 1e-4)],
                "phases": S * S,
                "joint_rank_1e-3": rank(_smaller_gram(joint), 1e-3),
                "phase0_rank_1e-3": rank(_smaller_gram(kernels[0]), 1e-3),
                "kernels": K * S * S,
                "beyond_nyquist": [
                    float(np.median(beyond_energy[lit] / energies[lit])),
                    float(beyond_energy.sum() / energies.sum()),
                ],
            }
        )
    return out


def _smaller_gram(matrix: np.ndarray) -> np.ndarray:
    """A·Aᵀ or Aᵀ·A, whichever is smaller: the same non-zero eigenvalues (A's squared singular values)."""
    return matrix @ matrix.T if matrix.shape[0] <= matrix.shape[1] else matrix.T @ matrix


def cross_coupled(model: LSVModel, cross_px: float) -> LSVModel:
    """``model`` with its stage and sensor axes coupled: A's zero terms set so that a point at the
    edge of the calibrated field moves ``cross_px`` px across (rows with x, columns with y)."""
    from dataclasses import replace

    A_poly = model.geometry.A_poly.copy()
    A_poly[0, 0, 0] += cross_px / max(abs(model.grid_x_mm[0]), abs(model.grid_x_mm[-1]))
    A_poly[0, 1, 1] += cross_px / max(abs(model.grid_y_mm[0]), abs(model.grid_y_mm[-1]))
    return replace(model, geometry=replace(model.geometry, A_poly=A_poly))


def finish(results: dict, args: argparse.Namespace) -> None:
    results["peak_rss_whole_run_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak RSS of the whole run (getrusage): {results['peak_rss_whole_run_gib']:.2f} GiB")
    print(json.dumps(results, indent=2))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
