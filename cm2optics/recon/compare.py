"""The model-based LSV reconstruction against the LSI baseline on a synthetic test set.

1. A test set made the paper's way (:mod:`cm2optics.synth`) through the LSV model, on Dask.
2. Each *run* (a forward model and a method: by default the 3D-LSV model with FISTA, and the
   V1 paper's depth-wise LSI model with its closed-form ADMM) reconstructs every measurement in
   its own Dask worker process, so that the worker's peak resident memory is the run's.
3. Each run is thresholded at its own F1-optimal global threshold over the test set (the paper's
   rule, applied alike to every run), evaluated volume by volume, pooled, and broken down by
   distance from the centre, depth, size and density, with recall/precision maps over the field.
   A CM²Net run is also scored at the operating threshold its weights carry, if any (chosen on
   validation volumes: :mod:`cm2optics.recon.net.operating`).

Writes ``comparison.json``, ``comparison.md`` and figures into ``out_dir``; reconstructions are
kept as ``.npy`` under ``out_dir/<run>/`` (``keep_volumes=False`` deletes them after evaluation).
"""

from __future__ import annotations

import json
import math
import resource
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.synth.config import SynthConfig

__all__ = ["DEFAULT_RUNS", "compare_baselines", "demo_baselines", "demo_net", "scaled_test_config"]

#: run name → forward model, method and options (see :class:`~cm2optics.recon.reconstruct.ReconOptions`).
DEFAULT_RUNS: dict[str, dict[str, Any]] = {
    "lsv-fista": {"forward": "lsv", "method": "fista", "l1": 0.02, "max_iter": 60},
    "lsi-admm": {"forward": "lsi", "method": "admm", "l1": 0.02, "max_iter": 30},
}


def scaled_test_config(model: Any, factor: float = 2.0, **changes: Any) -> SynthConfig:
    """The paper's test-set recipe with the field ÷ ``factor``, on the model's grid pitch, without
    views or patches (a test set needs measurements and emitters only)."""
    values = {"view_px": 0, "patch_px": 0, "store_volume": False} | changes
    return SynthConfig.scaled(factor, voxel_um=model.default_grid.voxel_um, **values)


def _peak_rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def _run(
    model_path: str, grid: dict, run: dict[str, Any], samples: list[str], out_dir: str, threads: int
) -> dict[str, Any]:
    """One run in one (fresh) worker process: reconstruct every sample, write the volumes."""
    import torch

    from cm2optics.formats.volume import VolumeGrid
    from cm2optics.recon.operators import load_operator
    from cm2optics.recon.reconstruct import ReconOptions, reconstruct
    from cm2optics.synth.dataset import read_sample

    torch.set_num_threads(threads)
    if run.get("method") == "net":
        return _run_net(model_path, VolumeGrid.from_dict(grid), run, samples, out_dir, threads)
    start = time.perf_counter()
    rss_start = _peak_rss_gib()
    operator = load_operator(model_path, VolumeGrid.from_dict(grid), forward=run["forward"])
    setup = time.perf_counter() - start
    options = ReconOptions(**{k: v for k, v in run.items() if k != "forward"})
    records = []
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    for path in samples:
        data = read_sample(path)
        volume, record = reconstruct(data["measurement"], operator, options)
        target = folder / (Path(path).stem + ".npy")
        np.save(target, volume)
        records.append(
            {
                "sample": Path(path).name,
                "volume": str(target),
                "seconds": record["seconds"],
                "iterations": record["iterations"],
                "converged": record["converged"],
                "variant": record["variant"],
            }
        )
    return {
        "setup_s": round(setup, 3),
        "records": records,
        "peak_rss_gib": round(_peak_rss_gib(), 3),
        "rss_at_start_gib": round(rss_start, 3),
        "memory_estimate": _estimate(operator, options),
        "threads": threads,
    }


def _run_net(model_path: str, grid: Any, run: dict[str, Any], samples: list[str], out_dir: str, threads: int):
    """A CM²Net run (``method: net``, ``weights``: a weights folder, ``preprocess``): one pass per
    sample through :func:`~cm2optics.recon.net.infer.reconstruct_with_net` with the test set's
    model, the volume resampled onto the test grid (centred on the axis; the network's lateral
    pitch is the model's object-side pixel, within 2 % of the test voxel)."""
    from cm2optics.lsv.model import load_model
    from cm2optics.recon.net.infer import reconstruct_with_net
    from cm2optics.recon.net.weights import load_weights
    from cm2optics.synth.dataset import read_sample

    start = time.perf_counter()
    rss_start = _peak_rss_gib()
    loaded = load_weights(run["weights"])
    model = load_model(model_path)
    net_voxel = loaded.config.synth.grid.voxel_um
    if not np.allclose(net_voxel, grid.voxel_um, rtol=0.02):
        raise ValueError(f"{run['weights']}: trained for {net_voxel}-µm voxels, the test grid has {grid.voxel_um}")
    setup = time.perf_counter() - start
    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    records = []
    for path in samples:
        data = read_sample(path)
        result = reconstruct_with_net(
            data["measurement"],
            loaded,
            model,
            preprocess=run.get("preprocess", "none"),
            grid=grid,
            view_px=run.get("view_px"),
        )
        target = folder / (Path(path).stem + ".npy")
        np.save(target, result.volume)
        seconds = result.seconds["total"]
        records.append(
            {
                "sample": Path(path).name,
                "volume": str(target),
                "seconds": seconds,
                "iterations": 1,
                "converged": True,
                "variant": "cm2net",
            }
        )
    parameters = sum(p.numel() for p in loaded.net.parameters())
    return {
        "setup_s": round(setup, 3),
        "records": records,
        "peak_rss_gib": round(_peak_rss_gib(), 3),
        "rss_at_start_gib": round(rss_start, 3),
        "memory_estimate": {"parameters": int(parameters), "total_gib": None},
        "threads": threads,
    }


def _estimate(operator: Any, options: Any) -> dict[str, float]:
    from cm2optics.recon.reconstruct import memory_estimate

    return {k: round(v, 4) if isinstance(v, float) else v for k, v in memory_estimate(operator, options).items()}


def compare_baselines(
    model_path: str | Path,
    out_dir: str | Path,
    *,
    n_volumes: int = 20,
    seed: int = 2024,
    config: SynthConfig | None = None,
    runs: dict[str, dict[str, Any]] | None = None,
    workers: int = 2,
    threads: int = 1,
    dask_address: str | None = None,
    keep_volumes: bool = True,
    reuse: bool = False,
    log: Callable[[str], None] | None = print,
    imaging: Any = None,
) -> dict[str, Any]:
    """Make the test set, run every run, evaluate; returns the summary (also ``comparison.json``).

    imaging: what makes the test set's measurements, in this process (a
    :class:`~cm2optics.synth.imaging.Imaging`, e.g. of frames traced by the emission simulator);
    default: the model at ``model_path``, on Dask workers. The runs reconstruct with ``model_path``."""
    from cm2optics.formats.atomic import write_json_atomic, write_text_atomic
    from cm2optics.lsv.model import load_model
    from cm2optics.metrics.plots import plot_breakdowns

    say = log or (lambda _: None)
    out_dir = Path(out_dir)
    model_path = Path(model_path).resolve()
    runs = runs or DEFAULT_RUNS
    model = load_model(model_path)
    config = config or scaled_test_config(model)
    grid = config.grid
    say(f"test set: {n_volumes} volumes, grid {grid.shape} of {'×'.join(f'{v:.3g}' for v in grid.voxel_um)} µm")
    manifest, samples, truths, densities = _test_set(
        config, imaging or model_path, out_dir, n_volumes, seed, workers=workers, dask_address=dask_address, say=say
    )
    results = _reconstruct_runs(
        model_path, grid, runs, samples, out_dir, threads=threads, dask_address=dask_address, reuse=reuse, say=say
    )

    summary: dict[str, Any] = {
        "model": str(model_path),
        "measurements": manifest["model"].get("kind"),
        "n_volumes": n_volumes,
        "seed": seed,
        "config": config.to_dict(),
        "grid": grid.to_dict(),
        "n_voxels": int(np.prod(grid.shape)),
        "n_emitters": int(sum(len(t) for t in truths)),
        "synth_s": round(float(manifest["seconds"]), 2),
        "runs": {},
    }
    breakdowns: dict[str, list] = {name: [] for name in ("lateral_mm", "depth_um", "size_um", "density")}
    for name, result in results.items():
        entry = _evaluate_run(name, runs[name], result, grid, truths, densities, out_dir, n_volumes)
        summary["runs"][name] = entry
        for b in ("lateral_mm", "depth_um", "size_um"):
            breakdowns[b].append(entry["breakdowns"][b])
        breakdowns["density"].append(entry["density"])
        if not keep_volumes:
            shutil.rmtree(out_dir / name, ignore_errors=True)
    plot_breakdowns(
        breakdowns,
        out_dir / "breakdowns.png",
        labels=list(results),
        title=f"{' vs '.join(results)} on {n_volumes} volumes",
    )
    write_json_atomic(out_dir / "comparison.json", summary)
    write_text_atomic(out_dir / "comparison.md", comparison_table(summary))
    say(comparison_table(summary))
    return summary


def _test_set(
    config: SynthConfig,
    model_path: Any,
    out_dir: Path,
    n_volumes: int,
    seed: int,
    *,
    workers: int,
    dask_address: str | None,
    say: Callable[[str], None],
) -> tuple[dict[str, Any], list[str], list, list[float]]:
    """The test set in ``out_dir/testset`` (made, or reused when it matches): its manifest, the
    sample paths, the true emitters of each sample and each sample's density (per mm²).
    ``model_path``: a model file, or an in-process imaging (made here; reused only when its source
    states a provenance, e.g. the traced design, binning and sensor window, and that matches)."""
    from cm2optics.synth.dataset import make_dataset, read_sample

    in_process = not isinstance(model_path, str | Path)
    manifest = _reusable_testset(out_dir / "testset", config, seed, n_volumes, _model_description(model_path))
    if manifest is None:
        manifest = make_dataset(
            config,
            model_path,
            out_dir / "testset",
            n_volumes,
            seed,
            workers=0 if in_process else workers,
            dask_address=None if in_process else dask_address,
        )
    else:
        say("reusing the test set already in " + str(out_dir / "testset"))
    samples = [str(out_dir / "testset" / "samples" / s["file"]) for s in manifest["samples"]]
    truths = [read_sample(p)["emitters"] for p in samples]
    densities = [s["density_per_mm2"] for s in manifest["samples"]]
    return manifest, samples, truths, densities


def _reconstruct_runs(
    model_path: Path,
    grid: Any,
    runs: dict[str, dict[str, Any]],
    samples: list[str],
    out_dir: Path,
    *,
    threads: int,
    dask_address: str | None,
    reuse: bool,
    say: Callable[[str], None],
) -> dict[str, Any]:
    """Every run's result (see :func:`_run`), reused from ``out_dir/<run>`` when allowed, else
    computed in one Dask worker process per run; in the order of ``runs``."""
    results: dict[str, Any] = {}
    todo = {}
    for name, run in runs.items():
        previous = _reusable_run(out_dir / name, run, samples) if reuse else None
        if previous is None:
            todo[name] = run
        else:
            results[name] = previous
            say(f"reusing the reconstructions in {out_dir / name}")
    if todo:
        say(f"reconstructing with {', '.join(todo)} (one Dask worker process each)")
        results.update(_submit_runs(model_path, grid, todo, samples, out_dir, threads, dask_address))
    return {name: results[name] for name in runs}


def _submit_runs(
    model_path: Path,
    grid: Any,
    todo: dict[str, dict[str, Any]],
    samples: list[str],
    out_dir: Path,
    threads: int,
    dask_address: str | None,
) -> dict[str, Any]:
    """Run each of ``todo`` on its own Dask worker (a local cluster unless ``dask_address``);
    each result is also written to ``out_dir/<run>/run.json``."""
    from dask.distributed import Client, LocalCluster

    from cm2optics.formats.atomic import write_json_atomic

    results: dict[str, Any] = {}
    cluster = None
    client = Client(dask_address) if dask_address else None
    if client is None:
        cluster = LocalCluster(n_workers=len(todo), threads_per_worker=1, processes=True, dashboard_address=":0")
        client = Client(cluster)
    try:
        addresses = sorted(client.scheduler_info()["workers"])
        futures = {
            name: client.submit(
                _run,
                str(model_path),
                grid.to_dict(),
                run,
                samples,
                str(out_dir / name),
                threads,
                workers=[addresses[i % len(addresses)]],
                allow_other_workers=False,
                pure=False,
            )
            for i, (name, run) in enumerate(todo.items())
        }
        for name, future in futures.items():
            results[name] = future.result()
            write_json_atomic(out_dir / name / "run.json", {"run": todo[name], "result": results[name]})
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return results


#: the per-volume scores averaged (and their spread) in each run's entry
_PER_VOLUME_KEYS = ("recall", "precision", "f1", "jaccard", "rmse_lateral_um", "rmse_axial_um")


def _evaluate_run(
    name: str,
    run: dict[str, Any],
    result: dict[str, Any],
    grid: Any,
    truths: list,
    densities: list[float],
    out_dir: Path,
    n_volumes: int,
) -> dict[str, Any]:
    """One run's entry of the summary: thresholded at its own F1-optimal threshold, scored volume
    by volume and pooled, broken down; draws its detection maps and its overlay of volume 0."""
    from cm2optics.metrics import (
        density_breakdown,
        evaluate_volume,
        f1_optimal_threshold,
        merge_evaluations,
        pooled_scores,
    )
    from cm2optics.metrics.breakdown import BREAKDOWNS, breakdown, detection_maps
    from cm2optics.metrics.plots import plot_maps, plot_overlay
    from cm2optics.metrics.scores import REPORTED_KEYS

    volumes = [np.load(r["volume"]) for r in result["records"]]
    pairs = list(zip(volumes, [grid] * len(volumes), truths, strict=True))
    threshold, _ = f1_optimal_threshold(pairs)
    evaluations = [evaluate_volume(v, grid, t, threshold) for v, _, t in pairs]
    pooled = pooled_scores(evaluations)
    per_volume = [e.metrics for e in evaluations]
    seconds = [r["seconds"] for r in result["records"]]
    entry = {
        "run": run,
        "variant": result["records"][0]["variant"],
        "threshold": threshold,
        **{k: pooled[k] for k in REPORTED_KEYS},
        "per_volume_mean": {k: _mean([m[k] for m in per_volume]) for k in _PER_VOLUME_KEYS},
        "per_volume_sd": {k: _sd([m[k] for m in per_volume]) for k in _PER_VOLUME_KEYS},
        "seconds_per_volume": round(float(np.mean(seconds)), 2),
        "seconds_total": round(float(np.sum(seconds)), 1),
        "setup_s": result["setup_s"],
        "iterations_mean": round(float(np.mean([r["iterations"] for r in result["records"]])), 1),
        "converged": int(sum(r["converged"] for r in result["records"])),
        "peak_rss_gib": result["peak_rss_gib"],
        "memory_estimate_gib": result["memory_estimate"],
        "threads": result["threads"],
        "breakdowns": {b: breakdown(evaluations, b) for b in BREAKDOWNS},
        "density": density_breakdown(evaluations, densities),
    }
    entry["at_operating_threshold"] = _at_operating_threshold(run, pairs, grid)
    merged = merge_evaluations(evaluations)
    plot_maps(detection_maps(merged, 250.0), out_dir / f"maps_{name}.png", title=f"{name}: {n_volumes} volumes")
    plot_overlay(
        volumes[0],
        evaluations[0],
        out_dir / f"overlay_{name}.png",
        title=f"{name}, volume 0 (threshold {threshold:.3g})",
    )
    return entry


def _at_operating_threshold(run: dict[str, Any], pairs: list, grid: Any) -> dict[str, Any] | None:
    """A CM²Net run scored at the operating threshold its weights carry (chosen on validation
    volumes, :mod:`cm2optics.recon.net.operating`); None for other runs and weights without one."""
    if run.get("method") != "net":
        return None
    from cm2optics.metrics import evaluate_volume, pooled_scores
    from cm2optics.metrics.scores import REPORTED_KEYS
    from cm2optics.recon.net.weights import load_weights

    operating = load_weights(run["weights"]).operating
    if operating is None:
        return None
    evaluations = [evaluate_volume(v, grid, t, operating.threshold) for v, _, t in pairs]
    pooled = pooled_scores(evaluations)
    per_volume = [e.metrics for e in evaluations]
    return {
        "threshold": operating.threshold,
        "rule": operating.rule,
        **{k: pooled[k] for k in REPORTED_KEYS},
        "per_volume_mean": {k: _mean([m[k] for m in per_volume]) for k in _PER_VOLUME_KEYS},
        "per_volume_sd": {k: _sd([m[k] for m in per_volume]) for k in _PER_VOLUME_KEYS},
    }


def _reusable_run(folder: Path, run: dict[str, Any], samples: list[str]) -> dict[str, Any] | None:
    """A run already made with the same options on the same samples (``run.json`` and volumes)."""
    path = folder / "run.json"
    if not path.is_file():
        return None
    saved = json.loads(path.read_text())
    result = saved.get("result", {})
    names = [r["sample"] for r in result.get("records", [])]
    if saved.get("run") != run or names != [Path(p).name for p in samples]:
        return None
    return result if all(Path(r["volume"]).is_file() for r in result["records"]) else None


def _model_description(model: Any) -> dict[str, Any] | None:
    """What a test set's manifest must record of the model that imaged it for the set to be
    reused: a model file's path, or an in-process source's kind and provenance (``None``: a source
    that states no provenance is never reused)."""
    if isinstance(model, str | Path):
        return {"path": str(model)}
    provenance = dict(getattr(model.source, "provenance", None) or {})
    if not provenance:
        return None
    return json.loads(json.dumps({"kind": type(model.source).__name__, "provenance": provenance}))


def _reusable_testset(
    folder: Path, config: SynthConfig, seed: int, n_volumes: int, model: dict[str, Any] | None
) -> dict[str, Any] | None:
    """The manifest of a test set already made with the same recipe, seed, size and model
    (``model``: :func:`_model_description`)."""
    path = folder / "manifest.json"
    if model is None or not path.is_file():
        return None
    manifest = json.loads(path.read_text())
    recorded = manifest.get("model", {})
    same = (
        manifest.get("config") == json.loads(json.dumps(config.to_dict()))
        and manifest.get("seed") == seed
        and manifest.get("n_volumes") == n_volumes
        and all(recorded.get(k) == v for k, v in model.items())
    )
    files = all((folder / "samples" / s["file"]).is_file() for s in manifest.get("samples", []))
    return manifest if same and files else None


def _mean(values: list[Any]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return round(float(np.mean(finite)), 4) if finite else None


def _sd(values: list[Any]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return round(float(np.std(finite)), 4) if len(finite) > 1 else None


def comparison_table(summary: dict[str, Any]) -> str:
    """A Markdown table of the runs."""
    header = "| run | recall | precision | F1 | Jaccard | lateral RMSE µm | axial RMSE µm | s / volume | iterations | peak RSS GiB |"
    lines = [header, "|" + "---|" * 10]
    for name, r in summary["runs"].items():

        def cell(key: str, r: dict[str, Any] = r) -> str:
            value = r[key]
            if value is None:
                return "—"
            spread = r["per_volume_sd"].get(key)
            return f"{value:.3f}" + (f" ± {spread:.3f}" if spread is not None else "")

        costs = f"{r['seconds_per_volume']:.1f} | {r['iterations_mean']:.0f} | {r['peak_rss_gib']:.2f} |"
        rows = [(f"{name} ({r['variant']})", r)]
        if r.get("at_operating_threshold"):
            at = r["at_operating_threshold"]
            rows.append((f"{name} at its weights' operating threshold {at['threshold']:.3g}", at))
        for label, scored in rows:
            lines.append(
                f"| {label} | {cell('recall', scored)} | {cell('precision', scored)} | {cell('f1', scored)} | "
                f"{cell('jaccard', scored)} | {cell('rmse_lateral_um', scored)} | {cell('rmse_axial_um', scored)} | {costs}"
            )
    grid = summary["grid"]
    lines += [
        "",
        f"{summary['n_volumes']} volumes, {summary['n_emitters']} emitters, grid {grid['shape']} of "
        f"{', '.join(f'{v:.3g}' for v in grid['voxel_um'])} µm ({summary['n_voxels'] / 1e6:.1f} M voxels); pooled scores "
        "± the sd over volumes; each run at its own F1-optimal global threshold"
        + (
            " (a network also at the operating threshold its weights carry, chosen on validation volumes)."
            if any(r.get("at_operating_threshold") for r in summary["runs"].values())
            else "."
        ),
    ]
    return "\n".join(lines) + "\n"


def demo_baselines(
    design: Any, folder: str | Path, model_path: str | Path | None, runs: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    """The demo's baseline comparison: one scaled-down volume made the paper's way through an LSV
    model (``model_path``; None or missing: a small analytic model of ``design`` built into
    ``folder``), reconstructed with each of ``runs`` (``forward`` and ReconOptions fields) and
    evaluated at each run's F1-optimal threshold. Returns the config, grid, sample, truth,
    chief rays (px), timings and per run its volume, record and evaluation. Runs on torch's
    default threads: FISTA through a traced ePSF model is large enough to use every core (91 s
    instead of 124 s for the demo's 30 iterations on two cores)."""
    from cm2optics.lsv.model import load_model
    from cm2optics.lsv.toy import analytic_lsv_model_file
    from cm2optics.recon.operators import load_operator
    from cm2optics.recon.reconstruct import ReconOptions, reconstruct
    from cm2optics.synth.dataset import make_dataset, read_sample
    from cm2optics.synth.imaging import Imaging

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    if model_path is None or not Path(model_path).is_file():
        model_path = analytic_lsv_model_file(
            folder / "lsv-analytic-b8.h5", design, binning=8, rank=6, lateral_nodes=7, depth_nodes=3
        )
        origin = "a small analytic model of this design (PSF scan of the closed-form CM²-like PSF, binned 8×)"
    else:
        origin = f"the LSV model {Path(model_path).name}"
    model = load_model(model_path)
    build_s = time.perf_counter() - start
    config = SynthConfig.scaled(
        2,
        voxel_um=model.default_grid.voxel_um,
        view_px=160,
        patch_px=64,
        patches_per_volume=4,
        density_per_mm2=(30.0, 30.0),
        fov_mm=(3.5, 3.5),
    )
    grid = config.grid
    start = time.perf_counter()
    manifest = make_dataset(config, Imaging(model, grid), folder / "synth", 1, seed=6, workers=0)
    synth_s = time.perf_counter() - start
    sample = read_sample(folder / "synth" / "samples" / manifest["samples"][0]["file"])
    truth = sample["emitters"]
    results = {}
    for name, run in runs.items():
        operator = load_operator(model_path, grid, forward=run["forward"])
        options = ReconOptions(**{k: v for k, v in run.items() if k != "forward"})
        volume, record = reconstruct(sample["measurement"], operator, options)
        results[name] = {"volume": volume, "record": record, "evaluation": _scored(volume, grid, truth)}
    return {
        "config": config,
        "grid": grid,
        "sample": sample,
        "truth": truth,
        "chief_rays_px": np.asarray(model.geometry.focus(0.0, 0.0, 0.0)),
        "origin": origin,
        "build_s": build_s,
        "synth_s": synth_s,
        "runs": results,
    }


@contextmanager
def _one_torch_thread() -> Iterator[None]:
    """Small tensors: one intra-op thread is faster, and kind to a shared machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _scored(volume: np.ndarray, grid: Any, truth: Any) -> Any:
    """The evaluation of one volume at its own F1-optimal threshold (``cm2 evaluate``'s default)."""
    from cm2optics.metrics import evaluate_volume, f1_optimal_threshold

    threshold, _ = f1_optimal_threshold([(volume, grid, truth)])
    return evaluate_volume(volume, grid, truth, threshold)


def demo_net(
    weights: str | Path,
    *,
    fov_mm: float = 0.6,
    view_px: int = 192,
    index: int = 0,
    fista_iterations: int = 30,
    l1: float = 0.02,
) -> dict[str, Any]:
    """The demo's CM²Net comparison on one measurement simulated at the weights' own geometry.

    The weights' synthetic recipe (forward model, voxels and planes, diameters, densities, noise)
    on a ``fov_mm`` disc with ``view_px``-px views, volume ``index`` of the test set's seed
    (:data:`~cm2optics.recon.net.testset.TEST_SEED`, which no training, validation or reference
    volume uses), imaged through the weights' forward model on the sensor window that holds the
    views; reconstructed by the network (:func:`~cm2optics.recon.net.infer.reconstruct_with_net`)
    and by FISTA (non-negativity + ``l1``, ``fista_iterations``) through that same model, each
    scored at its own F1-optimal threshold. Returns the config, grid, sample, truth and per run
    (``net``, ``fista``) its volume, grid and evaluation, and the seconds of each stage."""
    from cm2optics.recon.net.data import inference_model, sensor_window
    from cm2optics.recon.net.infer import reconstruct_with_net
    from cm2optics.recon.net.testset import TEST_SEED, check_seed
    from cm2optics.recon.net.weights import load_weights
    from cm2optics.recon.reconstruct import ReconOptions, reconstruct
    from cm2optics.synth.generate import synthesize_sample
    from cm2optics.synth.imaging import Imaging

    seconds: dict[str, float] = {}
    with _one_torch_thread():
        start = time.perf_counter()
        loaded = load_weights(weights)
        check_seed(TEST_SEED, loaded.config.seed)
        config = loaded.config.synth.with_changes(
            fov_mm=(fov_mm, fov_mm), view_px=view_px, patch_px=0, patches_per_volume=0, store_volume=False
        )
        grid = config.grid
        model = sensor_window(inference_model(loaded.config), view_px)
        seconds["model"] = time.perf_counter() - start
        start = time.perf_counter()
        sample = synthesize_sample(config, Imaging(model, grid), index, TEST_SEED)
        truth = sample.draw.emitters
        seconds["simulate"] = time.perf_counter() - start
        start = time.perf_counter()
        net = reconstruct_with_net(sample.measurement, loaded, model, view_px=view_px, name="the demo's measurement")
        seconds["net"] = time.perf_counter() - start
        start = time.perf_counter()
        fista, record = reconstruct(
            sample.measurement, model.operator(grid), ReconOptions(method="fista", l1=l1, max_iter=fista_iterations)
        )
        seconds["fista"] = time.perf_counter() - start
        start = time.perf_counter()
        runs = {
            "net": {"volume": net.volume, "grid": net.grid, "evaluation": _scored(net.volume, net.grid, truth)},
            "fista": {"volume": fista, "grid": grid, "evaluation": _scored(fista, grid, truth), "record": record},
        }
        seconds["score"] = time.perf_counter() - start
    return {
        "weights": loaded,
        "config": config,
        "grid": grid,
        "seed": TEST_SEED,
        "sample": sample,
        "truth": truth,
        "sensor_shape": tuple(int(v) for v in model.sensor_shape),
        "runs": runs,
        "seconds": seconds,
    }
