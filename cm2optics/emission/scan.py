"""Synthetic PSF calibration scans: a grid (or list) of source positions → a scan folder.

The folder is the measured-scan format of DESIGN.md (:mod:`cm2optics.formats.scan`): ``positions.csv``,
one 16-bit TIFF per position, ``scan.yaml``, written atomically by
:func:`~cm2optics.formats.scan.write_scan`; beside them ``montage.png`` and ``manifest.json``.

Each image is what the sensor would record of the source at that position: the simulated
frame (photons detected per emitted photon, :mod:`.psf`) × the source's photon rate
(``source_photons_per_ms``) × the exposure × the conversion gain (``counts_per_electron``), plus
``dark_level``, rounded to counts and clipped to the sensor's bit depth. Like the paper's
calibration script, the exposure adapts per position so that the brightest pixel reaches
``fill`` of full scale; ``exposure_ms`` records it, so ``PSFScan.normalised()`` (counts per ms)
is proportional to the PSF in every image. Synthetic images are noise-free. A design's
``as_built`` section is honoured: its geometry and transmissions by the tracer, its stray light
and pixel crosstalk on each frame (:mod:`cm2optics.optics.sensor_effects`), its leakage as
``leakage_counts_per_ms`` × the exposure added to the counts.

Positions run on Dask: a local cluster of one worker process per core by default, or the
scheduler at ``dask_address``. Each finished position is saved at once, atomically, in a work
folder beside the output (``.NAME.psf-work/``); a run that is interrupted (or fails) keeps
them, and the same command run again skips them and finishes the rest. The work folder is
removed once the scan is written; a run with other settings starts afresh.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import shutil
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import cm2optics
from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, Focus, PSFSettings, SensorGrid
from cm2optics.emission.source import PointSource, calibration_pinhole
from cm2optics.formats.atomic import write_atomic, write_json_atomic
from cm2optics.formats.scan import ScanError, ScanMeta, grid_axes_mm, write_scan
from cm2optics.optics import first_order
from cm2optics.optics.sensor_effects import apply_as_built
from cm2optics.progress import progress_bar

__all__ = [
    "ScanSettings",
    "calibration_grid_mm",
    "read_positions_csv",
    "simulate_position",
    "simulate_scan",
]

#: Axial extent of the calibration volume relative to the design's imaged depth: the paper
#: calibrates 1 mm for a 0.8-mm-deep imaged volume, so that the model interpolates, never
#: extrapolates, inside the imaged volume.
CALIBRATION_DEPTH_FACTOR = 1.25


@dataclass(frozen=True)
class ScanSettings:
    """How a synthetic scan turns PSFs into counts.

    psf: sampling of the PSFs (binning, bands, …).
    source: the point source (default: the paper's 5-µm calibration pinhole).
    fill: brightest pixel of each image as a fraction of full scale (0.05–1).
    source_photons_per_ms: photons the source emits per ms into its hemisphere (> 0).
    counts_per_electron: conversion gain, counts per photo-electron (> 0).
    dark_level: offset added to every pixel, counts (≥ 0).
    bit_depth: bits of the saved counts (None: the sensor's).
    max_exposure_ms: exposure of an image that receives no light, and the longest allowed, ms.
    """

    psf: PSFSettings = field(default_factory=PSFSettings)
    source: PointSource = field(default_factory=calibration_pinhole)
    fill: float = 0.8
    source_photons_per_ms: float = 1e7
    counts_per_electron: float = 0.25
    dark_level: float = 0.0
    bit_depth: int | None = None
    max_exposure_ms: float = 10000.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.fill) and 0.05 <= self.fill <= 1.0):
            raise ValueError(f"fill = {self.fill!r}: must lie within 0.05–1")
        for name in ("source_photons_per_ms", "counts_per_electron", "max_exposure_ms"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} = {value!r}: must be a finite number > 0")
        if not (math.isfinite(self.dark_level) and self.dark_level >= 0):
            raise ValueError(f"dark_level = {self.dark_level!r}: must be a finite number ≥ 0 (counts)")
        if self.bit_depth is not None and self.bit_depth not in (8, 10, 12, 14, 16):
            raise ValueError(f"bit_depth = {self.bit_depth!r}: must be one of 8, 10, 12, 14, 16")


# ----------------------------------------------------------------------------- positions


def calibration_grid_mm(
    design: SystemDesign, counts: tuple[int, int, int], field_mm: float | None = None, depth_mm: float | None = None
) -> np.ndarray:
    """Positions (N, 3) in mm of a calibration grid over the design's volume, z slowest, x fastest.

    Laterally the grid spans the square around the imaged field's disc (``volume.field_mm``;
    9 positions: −4 … 4 mm in 1-mm steps for cm2-v2), axially :data:`CALIBRATION_DEPTH_FACTOR`
    × ``volume.depth_mm`` centred on the nominal focal plane (11 positions: −0.5 … 0.5 mm in
    100-µm steps), as the paper's 9×9×11 scan. ``field_mm``/``depth_mm`` (mm) override the extents.

    The nominal focal plane (z = 0) is the design's plane of best focus
    (:func:`~cm2optics.optics.first_order.object_plane_z_mm`), where the PSFs are sharpest and
    where a lab centres its calibration, not the paraxial conjugate of the sensor, which lies
    :func:`~cm2optics.optics.first_order.focus_shift_mm` (≈ 0.85 mm for cm2-v2) farther from the
    device, outside the scanned depth: so the scan spans the usable depth symmetrically, and its
    centre has the design's magnification (0.58) and object pixel (4.1 µm).
    """
    nx, ny, nz = counts
    field_mm = design.volume.field_mm if field_mm is None else field_mm
    depth_mm = design.volume.depth_mm * CALIBRATION_DEPTH_FACTOR if depth_mm is None else depth_mm
    for name, value in (("field_mm", field_mm), ("depth_mm", depth_mm)):
        if not (math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} = {value!r}: must be a finite number ≥ 0 (mm)")

    def axis(n: int, span: float) -> np.ndarray:
        return np.zeros(1) if n == 1 else np.linspace(-span / 2, span / 2, n)

    z, y, x = np.meshgrid(axis(nz, depth_mm), axis(ny, field_mm), axis(nx, field_mm), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()]).round(9)


def read_positions_csv(path: str | Path) -> np.ndarray:
    """Positions (N, 3) in mm from a CSV with columns ``x_mm,y_mm,z_mm`` (others ignored).

    They must form a full grid (every combination of the unique x, y and z once), as a scan
    folder must (:func:`cm2optics.formats.scan.grid_axes_mm`); a single line of positions is a grid.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such positions file")
    with path.open(newline="") as handle:
        reader = csv.DictReader(row for row in handle if not row.lstrip().startswith("#"))
        columns = [c.strip() for c in reader.fieldnames or []]
        missing = [c for c in ("x_mm", "y_mm", "z_mm") if c not in columns]
        if missing:
            raise ValueError(
                f"{path}: needs columns x_mm,y_mm,z_mm (missing {', '.join(missing)}; found {','.join(columns)})"
            )
        rows = []
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            try:
                values = [float(row[c]) for c in ("x_mm", "y_mm", "z_mm")]
            except ValueError:
                raise ValueError(f"{path} line {line}: x_mm, y_mm, z_mm must be numbers (got {row})") from None
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f"{path} line {line}: positions must be finite (got {values})")
            rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no positions")
    positions = np.asarray(rows)
    check_positions(positions)
    return positions


def check_positions(positions_mm: np.ndarray) -> np.ndarray:
    """Validate (N, 3) positions (mm): finite, forming a full grid; returns them as float."""
    p = np.asarray(positions_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"positions have shape {p.shape}: must be (N, 3) with N ≥ 1 (x_mm, y_mm, z_mm)")
    if not np.all(np.isfinite(p)):
        raise ValueError("positions must be finite (no NaN)")
    try:
        grid_axes_mm(p)
    except ScanError as error:
        raise ValueError(f"{error}: a PSF scan must be a full grid of x, y, z") from None
    return p


# ----------------------------------------------------------------------------- one position

_MODELS: dict[str, EmissionModel] = {}


def _model(design: SystemDesign, settings: ScanSettings, key: str) -> EmissionModel:
    model = _MODELS.get(key)
    if model is None:
        _MODELS.clear()
        model = _MODELS[key] = EmissionModel(design, settings.source, settings=settings.psf)
    return model


def simulate_position(model: EmissionModel, position_mm: np.ndarray) -> list[Focus]:
    """The foci of one source position (object space, mm) — what a worker computes."""
    return model.foci(position_mm)


def _simulate_chunk(
    design: SystemDesign,
    settings: ScanSettings,
    key: str,
    items: list[tuple[int, np.ndarray]],
    threads: int | None = None,
) -> list[tuple[int, dict[str, np.ndarray], float]]:
    """Worker task: (index, packed foci, seconds) of each position of a chunk. ``threads``: Dr.Jit
    threads of this worker (1 on a local cluster of one worker per core, so that the workers'
    kernels do not fight over the cores; None: Dr.Jit's default)."""
    if threads is not None:
        _set_jit_threads(threads)
    model = _model(design, settings, key)
    out = []
    for index, position in items:
        start = time.perf_counter()
        foci = simulate_position(model, np.asarray(position, dtype=float))
        out.append((index, _pack(foci), time.perf_counter() - start))
    return out


def _set_jit_threads(threads: int) -> None:
    """Dr.Jit's thread pool size in this process (a no-op without a JIT variant)."""
    from cm2optics.optics.backend import is_jit

    if is_jit():
        import drjit as dr

        if dr.thread_count() != threads:
            dr.set_thread_count(threads)


def _pack(foci: list[Focus]) -> dict[str, np.ndarray]:
    packed = {
        "lenslet": np.array([f.lenslet for f in foci], dtype=np.int32),
        "origin": np.array([[f.row0, f.col0] for f in foci], dtype=np.int32).reshape(-1, 2),
        "shape": np.array([f.patch.shape for f in foci], dtype=np.int32).reshape(-1, 2),
        "data": np.concatenate([f.patch.ravel() for f in foci]).astype(np.float32) if foci else np.zeros(0, np.float32),
    }
    if foci and foci[0].epsf is not None:  # the fine-grid ePSF (emission.epsf), origin in fine samples
        S = foci[0].epsf.shape[0] // foci[0].patch.shape[0]
        packed["epsf_origin"] = packed["origin"] * S
        packed["epsf_shape"] = np.array([f.epsf.shape for f in foci], dtype=np.int32).reshape(-1, 2)
        packed["epsf_data"] = np.concatenate([f.epsf.ravel() for f in foci]).astype(np.float32)
    return packed


def _frame(packed: dict[str, np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    frame = np.zeros(shape)
    offset = 0
    for (r0, c0), (h, w) in zip(packed["origin"], packed["shape"], strict=True):
        frame[r0 : r0 + h, c0 : c0 + w] += packed["data"][offset : offset + h * w].reshape(h, w)
        offset += h * w
    return frame


# ----------------------------------------------------------------------------- scan


def _config_key(design: SystemDesign, settings: ScanSettings, positions: np.ndarray) -> str:
    text = json.dumps(
        {
            "design": design.parameter_hash(),
            "settings": asdict(settings),
            "positions": np.round(positions, 9).tolist(),
            "version": cm2optics.__version__,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _work_folder(out_dir: Path) -> Path:
    return out_dir.parent / f".{out_dir.name}.psf-work"


def _prepare_work(work: Path, key: str) -> set[int]:
    """Resume a work folder of the same configuration (the indices it holds), else start one."""
    config = work / "config.json"
    if work.is_dir():
        try:
            same = json.loads(config.read_text()).get("key") == key
        except (OSError, ValueError):
            same = False
        if same:
            done = set()
            for path in work.glob("pos_*.npz"):
                try:
                    done.add(int(path.stem.split("_")[1]))
                except ValueError:
                    continue
            return done
        shutil.rmtree(work)
    work.mkdir(parents=True)
    write_json_atomic(config, {"key": key})
    return set()


def _save_position(work: Path, index: int, packed: dict[str, np.ndarray], seconds: float) -> None:
    def write(tmp: Path) -> None:
        with tmp.open("wb") as handle:
            np.savez(handle, seconds=np.float64(seconds), **packed)

    write_atomic(work / f"pos_{index:05d}.npz", write)


def _load_position(work: Path, index: int) -> tuple[dict[str, np.ndarray], float]:
    with np.load(work / f"pos_{index:05d}.npz") as data:
        packed = {
            k: data[k]
            for k in ("lenslet", "origin", "shape", "data", "epsf_origin", "epsf_shape", "epsf_data")
            if k in data
        }
        return packed, float(data["seconds"])


def _client(dask_address: str | None, workers: int | None, processes: bool):
    from dask.distributed import Client, LocalCluster

    if dask_address:
        return Client(dask_address), None
    import dask

    n = workers or max(1, os.cpu_count() or 1)
    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536, which also freezes glibc's
    # mmap threshold: every large temporary array is then mapped and unmapped afresh, and each
    # position spent ≈ 0.25 s of system time on page faults (more than its computing). Workers
    # here keep glibc's adaptive defaults (a user's own setting of the variable still wins).
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=processes,
            dashboard_address=":0",
            **({"env": env} if processes else {}),
        )
    return Client(cluster), cluster


def simulate_scan(
    design: SystemDesign,
    positions_mm: np.ndarray,
    out_dir: str | Path,
    settings: ScanSettings | None = None,
    *,
    dask_address: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    chunk_size: int = 4,
    progress: bool = True,
    on_position: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Simulate a PSF scan of ``positions_mm`` (N, 3; object space, mm; a full grid) into
    ``out_dir`` (see the module docstring). Returns the manifest (also written as manifest.json).

    dask_address: an existing Dask scheduler (``tcp://host:8786``); None starts a local cluster
    of ``workers`` (default: one per core) processes (``processes=False``: threads of this
    process), each running Dr.Jit on one thread. chunk_size: positions per Dask task (1–64; a
    finished task's positions are saved at once, so an interrupted run loses at most one chunk
    per worker). on_position(done, total): called as positions finish (after the progress bar).
    """
    if not (isinstance(chunk_size, int) and 1 <= chunk_size <= 64):
        raise ValueError(f"chunk_size = {chunk_size!r}: must be an integer within 1–64")
    settings = settings or ScanSettings()
    positions = check_positions(positions_mm)
    out_dir = Path(os.path.abspath(out_dir))  # "." has no name: the work folder goes beside the absolute path
    if out_dir.exists() and not out_dir.is_dir():
        raise NotADirectoryError(f"{out_dir}: exists and is not a folder")
    model = EmissionModel(design, settings.source, settings=settings.psf)  # validates before any work
    for p in positions:
        model.device_point_mm(p)
    key = _config_key(design, settings, positions)
    work = _work_folder(out_dir)
    done = _prepare_work(work, key)
    todo = [i for i in range(len(positions)) if i not in done]
    started = time.perf_counter()
    bar = progress_bar("[bold]PSF scan", enabled=progress)
    if todo:
        client, cluster = _client(dask_address, workers, processes)
        try:
            threads = 1 if dask_address is None and processes else None
            futures = _submit_chunks(client, design, settings, key, positions, todo, chunk_size, threads)
            _collect(futures, work, done, len(positions), bar, on_position)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    compute_s = time.perf_counter() - started
    manifest = _write(design, settings, positions, out_dir, work, model.grid, compute_s)
    shutil.rmtree(work, ignore_errors=True)
    return manifest


def _submit_chunks(
    client,
    design: SystemDesign,
    settings: ScanSettings,
    key: str,
    positions: np.ndarray,
    todo: list[int],
    chunk_size: int,
    threads: int | None,
) -> list:
    """Submit the positions ``todo`` to ``client`` as Dask tasks of ``chunk_size`` positions (mm) each."""
    design_future = client.scatter(design, broadcast=True)
    chunks = [todo[i : i + chunk_size] for i in range(0, len(todo), chunk_size)]
    return [
        client.submit(
            _simulate_chunk,
            design_future,
            settings,
            key,
            [(i, positions[i]) for i in chunk],
            threads,
            pure=False,
        )
        for chunk in chunks
    ]


def _collect(
    futures: list,
    work: Path,
    done: set[int],
    total: int,
    bar,
    on_position: Callable[[int, int], None] | None,
) -> None:
    """Save each position to ``work`` as its task finishes, adding it to ``done`` and advancing ``bar``."""
    from dask.distributed import as_completed

    with bar:
        task = bar.add_task("scan", total=total, completed=len(done))
        for future in as_completed(futures):
            for index, packed, seconds in future.result():
                _save_position(work, index, packed, seconds)
                done.add(index)
                bar.advance(task)
                if on_position is not None:
                    on_position(len(done), total)


def _write(
    design: SystemDesign,
    settings: ScanSettings,
    positions: np.ndarray,
    out_dir: Path,
    work: Path,
    grid: SensorGrid,
    compute_s: float,
) -> dict[str, Any]:
    """Write the scan folder from the saved positions in ``work``; returns the manifest."""
    bits = settings.bit_depth or design.sensor.bit_depth
    images, exposures, seconds, energies, epsf_rows = _render_images(design, settings, positions, work, grid, bits)
    meta = ScanMeta(
        pixel_um=design.sensor.pixel_um * grid.binning,
        binning=grid.binning,
        bit_depth=bits,
        dark_level=settings.dark_level,
        extra=_extra_meta(design, settings, grid),
    )
    write_scan(out_dir, images, positions, exposures, meta)
    if settings.psf.oversample > 1:  # after write_scan, which replaces the folder
        from cm2optics.emission.epsf import EPSF_FILE, write_epsf_file

        units = "counts per ms (the scan's normalised units)"
        write_atomic(out_dir / EPSF_FILE, lambda tmp: write_epsf_file(tmp, settings.psf.oversample, units, epsf_rows))
    write_montage(out_dir / "montage.png", images, positions, exposures, settings.dark_level)
    del images
    manifest = _manifest(design, settings, positions, grid, compute_s, seconds, energies, exposures)
    write_json_atomic(out_dir / "manifest.json", manifest)
    return manifest


def _render_images(
    design: SystemDesign,
    settings: ScanSettings,
    positions: np.ndarray,
    work: Path,
    grid: SensorGrid,
    bits: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[dict[str, np.ndarray]]]:
    """The sensor images (counts, uint16 memmap in ``work``), exposures (ms), seconds, energies and ePSF rows."""
    full = 2**bits - 1
    rows, cols = grid.shape
    images = np.lib.format.open_memmap(
        work / "images.npy", mode="w+", dtype=np.uint16, shape=(len(positions), rows, cols)
    )
    exposures = np.empty(len(positions))
    seconds = np.empty(len(positions))
    energies = np.empty(len(positions))
    epsf_rows: list[dict[str, np.ndarray]] = []
    headroom = full * settings.fill - settings.dark_level
    if headroom <= 0:
        raise ValueError(
            f"dark_level = {settings.dark_level} leaves no room below {settings.fill:g} of full scale ({full} counts)"
        )
    for i in range(len(positions)):
        packed, seconds[i] = _load_position(work, i)
        frame = apply_as_built(_frame(packed, (rows, cols)), design.as_built, grid.pitch_mm * 1000.0)
        energies[i] = frame.sum()
        rate = frame.max() * settings.source_photons_per_ms * settings.counts_per_electron  # counts per ms at the peak
        exposure = settings.max_exposure_ms if rate <= 0 else min(headroom / rate, settings.max_exposure_ms)
        exposures[i] = float(f"{exposure:.6g}")
        counts = (
            frame * (settings.source_photons_per_ms * settings.counts_per_electron * exposures[i])
            + settings.dark_level
            + design.as_built.leakage_counts_per_ms * exposures[i]
        )
        images[i] = np.clip(np.rint(counts), 0, full).astype(np.uint16)
        if settings.psf.oversample > 1:
            epsf_rows.append(_epsf_row(packed, settings))
    images.flush()
    return images, exposures, seconds, energies, epsf_rows


def _epsf_row(packed: dict[str, np.ndarray], settings: ScanSettings) -> dict[str, np.ndarray]:
    """One position's packed ePSF crops, scaled from photons per emitted photon to counts per ms."""
    unit = settings.source_photons_per_ms * settings.counts_per_electron  # → counts per ms
    return {
        "lenslet": packed["lenslet"],
        "origin": packed.get("epsf_origin", np.zeros((0, 2), np.int32)),
        "shape": packed.get("epsf_shape", np.zeros((0, 2), np.int32)),
        "data": packed.get("epsf_data", np.zeros(0, np.float32)) * np.float32(unit),
    }


def _manifest(
    design: SystemDesign,
    settings: ScanSettings,
    positions: np.ndarray,
    grid: SensorGrid,
    compute_s: float,
    seconds: np.ndarray,
    energies: np.ndarray,
    exposures: np.ndarray,
) -> dict[str, Any]:
    """The scan's manifest.json: inputs, settings, timings (s) and photometric metrics."""
    return {
        "stage": "emission.psf_scan",
        "package_version": cm2optics.__version__,
        "design": design.name,
        "parameter_hash": design.parameter_hash(),
        "inputs": {"positions": len(positions), "grid_shape": [len(a) for a in grid_axes_mm(positions)]},
        "settings": json.loads(json.dumps(asdict(settings), default=str)),
        "timings": {
            "wall_s": round(compute_s, 3),
            "per_position_s_mean": round(float(seconds.mean()), 4),
            "per_position_s_max": round(float(seconds.max()), 4),
        },
        "metrics": {
            "detected_per_emitted_photon_max": float(energies.max()),
            "detected_per_emitted_photon_min": float(energies.min()),
            "exposure_ms_min": float(exposures.min()),
            "exposure_ms_max": float(exposures.max()),
        },
        "files": ["positions.csv", "scan.yaml", "montage.png"],
    }


def _extra_meta(design: SystemDesign, settings: ScanSettings, grid: SensorGrid) -> dict[str, Any]:
    source = settings.source
    return {
        "synthetic": True,
        "generator": f"cm2optics {cm2optics.__version__} (cm2optics.emission)",
        "design": design.name,
        "design_hash": design.parameter_hash(),
        "lenslets": [design.mla.rows, design.mla.cols],
        "sensor_width_px": design.sensor.width_px,
        "sensor_height_px": design.sensor.height_px,
        "sensor_pixel_um": design.sensor.pixel_um,
        "image_orientation": (
            "sensor frame of the device: column index along +x, row index along +y, the optical axis of the "
            "central lenslet at the frame centre (col (W-1)/2, row (H-1)/2 in sensor pixels); each lenslet "
            "inverts, so a source moved +x moves every focus towards -x"
        ),
        "position_units": (
            "mm, object space: x, y from the central lenslet's axis, z from the nominal focal plane (the plane "
            "of best focus), +z towards the device"
        ),
        "focal_plane": "best focus: least RMS wavefront error of the on-axis image (design wavelength)",
        "focal_plane_height_mm": round(float(first_order.object_plane_z_mm(design)), 6),
        "paraxial_focal_plane_z_mm": round(float(-first_order.focus_shift_mm(design)), 6),
        "magnification": round(first_order.magnification(design), 6),
        "object_pixel_um": round(first_order.object_pixel_um(design), 6),
        "source_diameter_um": source.diameter_um,
        "source_profile": source.profile.describe(),
        "source_photons_per_ms": settings.source_photons_per_ms,
        "counts_per_electron": settings.counts_per_electron,
        "counts": "electrons x counts_per_electron + dark_level; exposure chosen per image for the peak at fill of full scale",
        "fill": settings.fill,
        "noise": "none",
        **({"epsf_oversample": settings.psf.oversample, "epsf_file": "epsf.h5"} if settings.psf.oversample > 1 else {}),
    }


def write_montage(
    path: Path,
    images: np.ndarray,
    positions_mm: np.ndarray,
    exposure_ms: np.ndarray,
    dark_level: float = 0.0,
    max_tiles: int = 81,
    tile_px: int = 160,
) -> Path:
    """A PNG of a scan's images (counts per ms above the dark level, square root, each tile
    scaled to its own maximum): at most ``max_tiles`` of them — for a grid, the plane nearest
    the focal plane, laid out row by row as the positions run (x fastest)."""
    from matplotlib.figure import Figure  # no pyplot: a notebook's backend stays as it is

    positions_mm = np.asarray(positions_mm, dtype=float)
    xs, ys, zs = grid_axes_mm(positions_mm)
    z_mid = zs[np.argmin(np.abs(zs))]
    pick = [i for i, p in enumerate(positions_mm) if abs(p[2] - z_mid) < 1e-9][:max_tiles]
    nx = len(xs) if len(pick) == len(xs) * len(ys) else int(math.ceil(math.sqrt(len(pick))))
    ny = int(math.ceil(len(pick) / nx))
    fig = Figure(figsize=(1.6 * nx + 0.4, 1.1 * ny + 0.6))
    axes = fig.subplots(ny, nx, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for n, i in enumerate(pick):
        img = np.clip(np.asarray(images[i], dtype=np.float32) - dark_level, 0, None) / float(exposure_ms[i])
        step = max(1, int(math.ceil(img.shape[1] / tile_px)))
        h, w = (img.shape[0] // step) * step, (img.shape[1] // step) * step
        small = img[:h, :w].reshape(h // step, step, w // step, step).max(axis=(1, 3))
        ax = axes.ravel()[n]
        ax.imshow(np.sqrt(small / small.max()) if small.max() > 0 else small, cmap="magma", interpolation="nearest")
        x, y, _ = positions_mm[i]
        ax.set_title(f"({x:g}, {y:g})", fontsize=6)
    fig.suptitle(
        f"PSF scan at z = {z_mid:g} mm: source (x, y) in mm; sqrt of counts/ms, each tile to its max", fontsize=8
    )
    fig.tight_layout()

    def write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=110, format="png")

    return write_atomic(Path(path), write)


def positions_from_iterable(rows: Iterable[Iterable[float]]) -> np.ndarray:
    """(N, 3) float positions from rows of (x_mm, y_mm, z_mm), validated as a grid."""
    return check_positions(np.asarray([list(r) for r in rows], dtype=float))
