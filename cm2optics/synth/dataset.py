"""A synthetic data set on disk, made in parallel on Dask.

Layout of ``out_dir``::

    manifest.json          config, seed, model (path + SHA-256), per-sample summaries and
                           content hashes, timings, package version
    dataset.h5             one entry point: the config, external links to every sample,
                           ``patch_index`` (n, 2) = (sample, patch) over the whole set
    samples/sample_00000.h5  one file per volume, written atomically by the worker that made it

A sample file (``format = "cm2optics-synth-sample"``) holds ``emitters`` (N, 5: x_um, y_um,
z_um, diameter_um, intensity), ``measurement`` (H, W, normalised, noisy), ``views`` (J, V, V,
noisy, cropped at the chief rays), ``demixed`` (J, V, V, each lenslet's clean image, the
demixing target), ``volume`` (z, y, x, emission per voxel in emitter-intensity units; optional)
and ``patches/{views, demixed, volume, origin, voxel_origin}``; attributes give the sample's
field, density, ``image_scale`` (model units per normalised unit), grid and config.

Every array is stored without timestamps, and the manifest's ``content_sha256`` hashes the
arrays themselves: the same seed, config and model give the same hashes, whatever the number of
workers. Workers are a local Dask cluster by default or an existing scheduler
(``dask_address``); ``workers=0`` makes the samples in this process (tests, tiny sets).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

import cm2optics
from cm2optics.errors import UserError
from cm2optics.formats.atomic import write_atomic, write_json_atomic
from cm2optics.formats.emitters import EMITTER_COLUMNS, Emitters
from cm2optics.synth.config import SynthConfig
from cm2optics.synth.generate import Sample, synthesize_sample
from cm2optics.synth.imaging import Imaging, load_imaging

__all__ = ["SAMPLE_FORMAT", "DatasetError", "make_dataset", "read_sample", "write_sample"]

SAMPLE_FORMAT = "cm2optics-synth-sample"
DATASET_FORMAT = "cm2optics-synth-dataset"
VERSION = 1
#: Manifest fields that fix a data set's content: a rerun into the same folder must match them.
INPUT_FIELDS = ("seed", "config", "model_sha256")


class DatasetError(UserError):
    """A data set folder or sample file that cannot be used; the message names the file and field."""


def _dataset(group: h5py.Group, name: str, data: np.ndarray, chunks: Any = True, compress: bool = True) -> None:
    kwargs: dict[str, Any] = {"track_times": False, "fillvalue": 0}
    if compress and data.size > 1024:
        kwargs.update(compression="lzf", shuffle=True, chunks=chunks)
    group.create_dataset(name, data=data, **kwargs)


def _content_hash(arrays: dict[str, np.ndarray]) -> str:
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(name.encode())
        digest.update(str(array.dtype).encode() + str(array.shape).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _arrays(sample: Sample) -> dict[str, np.ndarray]:
    e = sample.draw.emitters
    arrays = {"emitters": np.stack([getattr(e, c) for c in EMITTER_COLUMNS], axis=1), "measurement": sample.measurement}
    for name in ("views", "demixed", "volume"):
        value = getattr(sample, name)
        if value is not None:
            arrays[name] = value
    for name, value in sample.patches.items():
        arrays[f"patches/{name}"] = value
    return arrays


def write_sample(path: str | Path, sample: Sample, config: SynthConfig) -> dict[str, Any]:
    """Write one sample file atomically; returns its summary with ``content_sha256``."""
    arrays = _arrays(sample)
    digest = _content_hash(arrays)
    grid = config.grid

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w", track_order=False) as f:
            f.attrs["format"] = SAMPLE_FORMAT
            f.attrs["version"] = VERSION
            f.attrs["index"] = sample.index
            f.attrs["seed"] = sample.seed
            f.attrs["fov_mm"] = sample.draw.fov_mm
            f.attrs["density_per_mm2"] = sample.draw.density_per_mm2
            f.attrs["area_mm2"] = sample.draw.area_mm2
            f.attrs["image_scale"] = sample.image_scale
            f.attrs["grid"] = json.dumps(grid.to_dict())
            f.attrs["config"] = json.dumps(config.to_dict())
            f.attrs["emitter_columns"] = ",".join(EMITTER_COLUMNS)
            f.attrs["content_sha256"] = digest
            for name, data in arrays.items():
                if name == "volume":
                    _dataset(f, name, data, chunks=(1,) + tuple(min(n, 256) for n in data.shape[1:]))
                elif name.startswith("patches/"):
                    _dataset(f, name, data, chunks=(1,) + data.shape[1:])
                else:
                    _dataset(f, name, data)

    write_atomic(Path(path), write)
    summary = sample.summary()
    summary["file"] = Path(path).name
    summary["content_sha256"] = digest
    return summary


def read_sample(path: str | Path, *, verify: bool = True) -> dict[str, Any]:
    """A sample file's arrays and attributes (``emitters`` as :class:`Emitters`).

    verify: check the arrays against the ``content_sha256`` the file (or, for older files, the
    data set's ``manifest.json``) records; a mismatch raises :class:`DatasetError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such sample file")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != SAMPLE_FORMAT:
                raise DatasetError(f"{path}: not a synthetic sample (format = {f.attrs.get('format')!r})")
            out: dict[str, Any] = {k: (json.loads(v) if k in ("grid", "config") else v) for k, v in f.attrs.items()}
            arrays = {
                name: f[name][()] for name in ("emitters", "measurement", "views", "demixed", "volume") if name in f
            }
            if "patches" in f:
                arrays |= {f"patches/{k}": f["patches"][k][()] for k in f["patches"]}
    except OSError as error:
        raise DatasetError(f"{path}: not a readable sample file ({error})") from None
    if verify:
        expected = out.get("content_sha256") or _manifest_hash(path)
        if expected is not None and _content_hash(arrays) != expected:
            raise DatasetError(
                f"{path}: content_sha256 does not match the arrays (the file was changed or corrupted after it was written)"
            )
    table = arrays.pop("emitters")
    out |= {k: v for k, v in arrays.items() if not k.startswith("patches/")}
    if any(k.startswith("patches/") for k in arrays):
        out["patches"] = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("patches/")}
    out["emitters"] = Emitters(*table.T) if len(table) else Emitters(*(np.zeros(0) for _ in EMITTER_COLUMNS))
    return out


def _manifest_hash(path: Path) -> str | None:
    """The ``content_sha256`` that the data set's manifest records for sample ``path``, if any."""
    manifest = path.parent.parent / "manifest.json"
    try:
        samples = json.loads(manifest.read_text()).get("samples", [])
    except (OSError, ValueError):
        return None
    return next((s.get("content_sha256") for s in samples if s.get("file") == path.name), None)


def _inputs(manifest: dict[str, Any]) -> dict[str, Any]:
    return {
        "seed": manifest.get("seed"),
        "config": manifest.get("config"),
        "model_sha256": (manifest.get("model") or {}).get("sha256"),
    }


def _check_resume(out_dir: Path, manifest: dict[str, Any]) -> None:
    """Refuse to write into a folder whose manifest records other inputs (a rerun with the same
    inputs remakes the same files)."""
    path = out_dir / "manifest.json"
    if not path.is_file():
        return
    try:
        before = json.loads(path.read_text())
    except ValueError:
        raise DatasetError(f"{path}: not valid JSON; remove the folder or write elsewhere") from None
    if before.get("format") != DATASET_FORMAT:
        raise DatasetError(f"{path}: not a synthetic data set manifest; write elsewhere")
    old, new = _inputs(before), _inputs(manifest)
    for field in INPUT_FIELDS:
        if field == "model_sha256" and (old[field] is None or new[field] is None):
            continue
        if old[field] != new[field]:
            if field == "config":
                changed = sorted(
                    k
                    for k in set(old["config"] or {}) | set(new["config"])
                    if (old["config"] or {}).get(k) != new["config"].get(k)
                )
                what = f"config ({', '.join(changed)})"
            else:
                what = f"{field} ({old[field]!r} there, {new[field]!r} now)"
            raise DatasetError(
                f"{out_dir}: holds a data set made with another {what}; samples of two runs would mix. "
                "Rerun with the same inputs to resume, or write into a new folder"
            )


# ----------------------------------------------------------------------------- tasks


def _make_one(
    config_dict: dict[str, Any], model: str | Imaging, index: int, seed: int, path: str, threads: int | None
) -> dict[str, Any]:
    """One Dask task: make sample ``index`` and write it to ``path``."""
    if threads:
        import torch

        torch.set_num_threads(threads)
    config = SynthConfig.from_dict(config_dict)
    imaging = model if isinstance(model, Imaging) else load_imaging(model, config.grid, config.render)
    sample = synthesize_sample(config, imaging, index, seed)
    return write_sample(path, sample, config)


def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _client(dask_address: str | None, workers: int) -> tuple[Any, Any]:
    from dask.distributed import Client, LocalCluster

    if dask_address:
        return Client(dask_address), None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster), cluster


def _check_arguments(
    n_volumes: int, seed: int, workers: int, model: str | Path | Imaging, dask_address: str | None
) -> None:
    """A ValueError for a count, seed or worker number out of range, or an in-process model on Dask."""
    if n_volumes < 1:
        raise ValueError(f"n_volumes = {n_volumes}: must be ≥ 1")
    if seed < 0:
        raise ValueError(f"seed = {seed}: must be ≥ 0")
    if workers < 0:
        raise ValueError(f"workers = {workers}: must be ≥ 0")
    if isinstance(model, Imaging) and (workers or dask_address):
        raise ValueError("an in-process model runs with workers = 0; give a model file to use Dask workers")


def _model_reference(model: str | Path | Imaging, config: SynthConfig) -> tuple[str | Imaging, dict[str, Any]]:
    """What the workers load (the model file's absolute path, or the in-process model) and the
    manifest's description of it; a model file is loaded once here, to fail early."""
    if isinstance(model, Imaging):
        provenance = dict(getattr(model.source, "provenance", None) or {})
        return model, {"path": None, "kind": type(model.source).__name__, "provenance": provenance}
    model_path = Path(model).resolve()
    imaging = load_imaging(model_path, config.grid, config.render)  # fail early, in this process
    return str(model_path), {
        "path": str(model_path),
        "sha256": _file_sha256(model_path),
        "kind": type(imaging.source).__name__,
        "render": imaging.render,
        "sensor_shape": list(imaging.sensor_shape),
        "n_lenslets": imaging.n_lenslets,
    }


def _make_on_dask(
    summaries: list[dict[str, Any] | None],
    config_dict: dict[str, Any],
    model_ref: str | Imaging,
    paths: list[Path],
    seed: int,
    dask_address: str | None,
    workers: int,
    progress: Callable[[int, int], None] | None,
) -> None:
    """Make every sample on Dask workers, filling ``summaries`` (by sample index) as they finish."""
    from dask.distributed import as_completed

    client, cluster = _client(dask_address, workers)
    try:
        threads = 1 if cluster is not None else None
        futures = {
            client.submit(_make_one, config_dict, model_ref, i, seed, str(p), threads, pure=False): i
            for i, p in enumerate(paths)
        }
        done = 0
        for future in as_completed(futures):
            summaries[futures[future]] = future.result()
            done += 1
            if progress:
                progress(done, len(paths))
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def make_dataset(
    config: SynthConfig,
    model: str | Path | Imaging,
    out_dir: str | Path,
    n_volumes: int,
    seed: int = 0,
    *,
    dask_address: str | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Make ``n_volumes`` samples into ``out_dir`` (see the module docstring); returns the manifest.

    model: a model file (LSV model or PSF stack; each worker loads it once) or an in-process
    :class:`Imaging` (only with ``workers=0``). workers: local Dask workers (0: this process).
    """
    _check_arguments(n_volumes, seed, workers, model, dask_address)
    out_dir = Path(out_dir)
    samples_dir = out_dir / "samples"
    samples_dir.mkdir(parents=True, exist_ok=True)
    model_ref, model_info = _model_reference(model, config)
    config_dict = config.to_dict()
    header = {
        "format": DATASET_FORMAT,
        "version": VERSION,
        "cm2optics_version": cm2optics.__version__,
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "seed": seed,
        "n_volumes": n_volumes,
        "config": config_dict,
        "grid": config.grid.to_dict(),
        "model": model_info,
    }
    _check_resume(out_dir, json.loads(json.dumps(header)))
    write_json_atomic(out_dir / "manifest.json", header | {"complete": False, "samples": []})
    paths = [samples_dir / f"sample_{i:05d}.h5" for i in range(n_volumes)]
    start = time.perf_counter()
    summaries: list[dict[str, Any] | None] = [None] * n_volumes
    try:
        if workers == 0 and not dask_address:
            for i, path in enumerate(paths):
                summaries[i] = _make_one(config_dict, model_ref, i, seed, str(path), None)
                if progress:
                    progress(i + 1, n_volumes)
        else:
            _make_on_dask(summaries, config_dict, model_ref, paths, seed, dask_address, workers, progress)
    except BaseException:
        for tmp in samples_dir.glob(".sample_*.tmp*"):
            tmp.unlink(missing_ok=True)
        raise
    elapsed = time.perf_counter() - start
    done_summaries = [s for s in summaries if s is not None]
    patch_index = np.array(
        [(s["index"], p) for s in done_summaries for p in range(s["n_patches"])], dtype=np.int32
    ).reshape(-1, 2)
    _write_index(out_dir / "dataset.h5", config, seed, paths, patch_index)
    manifest = header | {
        "complete": True,
        "workers": "in-process"
        if workers == 0 and not dask_address
        else (dask_address or f"local cluster × {workers}"),
        "seconds": round(elapsed, 3),
        "seconds_per_volume": round(elapsed / n_volumes, 3),
        "n_patches": int(len(patch_index)),
        "n_emitters": int(sum(s["n_emitters"] for s in done_summaries)),
        "samples": done_summaries,
    }
    write_json_atomic(out_dir / "manifest.json", manifest)
    return manifest


def _write_index(path: Path, config: SynthConfig, seed: int, samples: list[Path], patch_index: np.ndarray) -> None:
    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = DATASET_FORMAT
            f.attrs["version"] = VERSION
            f.attrs["seed"] = seed
            f.attrs["config"] = json.dumps(config.to_dict())
            group = f.create_group("samples")
            for sample in samples:
                group[sample.stem] = h5py.ExternalLink(f"samples/{sample.name}", "/")
            f.create_dataset("patch_index", data=patch_index, track_times=False)

    write_atomic(path, write)
