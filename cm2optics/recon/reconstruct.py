"""One measurement → one volume with a model-based baseline, memory checked before it starts.

The measurement is brought to the model's units first: a constant background (the sensor's
offset; ``"auto"``: the image median, right for sparse scenes) is removed (Richardson–Lucy keeps
it in its model instead), and the image is scaled to a peak of 1; the volume is scaled back, so
it is in the measurement's units per unit of the model's response.

``method``: ``fista``, ``admm`` or ``rl`` (:mod:`cm2optics.recon.solvers`). ``admm`` on a
depth-wise LSI operator is the V1 paper's closed-form ADMM; on any other operator (the LSV
model) it is ADMM with a conjugate-gradient x-update.

Memory: :func:`memory_estimate` counts the volume-sized arrays a method keeps (and the
operator's own buffers where it says how big they are); a run whose estimate exceeds
``max_memory_gib`` stops before it starts with a message naming what to change.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cm2optics.errors import UserError
from cm2optics.formats.operator import VolumeOperator
from cm2optics.lsv.lsi import DepthwiseConvOperator
from cm2optics.recon.solvers import Progress, SolverResult, Stopping, admm, admm_lsi, fista, richardson_lucy

__all__ = [
    "METHODS",
    "ReconOptions",
    "check_device",
    "check_memory",
    "memory_estimate",
    "reconstruct",
    "reconstruct_file",
]

METHODS = ("fista", "admm", "rl")
#: Volume-sized float32 arrays each method keeps (without TV, extra with TV).
_COPIES = {"fista": (6, 8), "admm": (9, 10), "rl": (5, 5)}
_LSI_COPIES = (14, 10)  # canvas-sized (z-padded) arrays of the closed-form LSI ADMM, complex counted twice


@dataclass(frozen=True)
class ReconOptions:
    """method: fista | admm | rl. l1, tv: weights relative to ‖Aᵀb‖∞ (RL: to mean Aᵀ1).
    max_iter, tol, patience: the stopping rule. background: ``"auto"`` (median), a number in
    the measurement's units, or ``"none"``. max_memory_gib: refuse runs estimated above it.
    tv_iterations: FGP iterations of FISTA's TV prox. cg_iterations: ADMM's inner CG steps.
    mu: ADMM penalty (relative)."""

    method: str = "fista"
    l1: float = 0.02
    tv: float = 0.0
    max_iter: int = 100
    tol: float = 1e-3
    patience: int = 3
    background: str | float = "auto"
    max_memory_gib: float = 20.0
    tv_iterations: int = 10
    cg_iterations: int = 3
    mu: float = 0.05

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method = {self.method!r}: must be one of {', '.join(METHODS)}")
        for name in ("l1", "tv"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} = {value}: must be a finite number ≥ 0")
        if not (self.max_memory_gib > 0):
            raise ValueError(f"max_memory_gib = {self.max_memory_gib}: must be > 0")
        if not (self.mu > 0 and math.isfinite(self.mu)):
            raise ValueError(f"mu = {self.mu}: must be a finite number > 0")
        Stopping(self.max_iter, self.tol, self.patience)
        if isinstance(self.background, str) and self.background not in ("auto", "none"):
            try:
                float(self.background)
            except ValueError:
                raise ValueError(f"background = {self.background!r}: give 'auto', 'none' or a number") from None

    @property
    def stopping(self) -> Stopping:
        return Stopping(self.max_iter, self.tol, self.patience)


def _operator_bytes(operator: VolumeOperator) -> int:
    if hasattr(operator, "memory_bytes"):
        return int(operator.memory_bytes()) + int(getattr(operator, "transient_bytes", lambda: 0)())
    if hasattr(operator, "canvas_shape") and hasattr(operator, "depth_nodes") and hasattr(operator, "n_lenslets"):
        Hc, Wc = operator.canvas_shape  # the LSV operator's per-lenslet, per-depth-node spectra
        return int(operator.n_lenslets * len(operator.depth_nodes) * Hc * (Wc // 2 + 1) * 8)
    return 0


def memory_estimate(operator: VolumeOperator, options: ReconOptions) -> dict[str, float]:
    """Estimated peak bytes: ``volume_copies`` × volume + the operator's buffers (GiB)."""
    nz, ny, nx = operator.grid.shape
    if options.method == "admm" and isinstance(operator, DepthwiseConvOperator):
        Hc, Wc = operator.canvas_shape
        unit = (nz + 2) * Hc * Wc * 4
        copies = _LSI_COPIES[0] + (_LSI_COPIES[1] if options.tv > 0 else 0)
    else:
        unit = nz * ny * nx * 4
        base, extra = _COPIES[options.method]
        copies = base + (extra if options.tv > 0 else 0)
    op_bytes = _operator_bytes(operator)
    total = copies * unit + op_bytes
    return {
        "volume_copies": copies,
        "array_gib": unit / 2**30,
        "operator_gib": op_bytes / 2**30,
        "total_gib": total / 2**30,
    }


def check_memory(grid: Any, options: ReconOptions) -> None:
    """Refuse, before anything is allocated, a run whose volume-sized arrays alone exceed
    ``options.max_memory_gib`` on ``grid`` (a lower bound of :func:`memory_estimate`)."""
    if grid is None:
        return
    nz, ny, nx = (int(n) for n in grid.shape)
    base, extra = _COPIES[options.method]
    gib = (base + (extra if options.tv > 0 else 0)) * nz * ny * nx * 4 / 2**30
    if gib > options.max_memory_gib:
        raise UserError(
            f"{options.method} on a {nz}×{ny}×{nx} grid needs ≥ {gib:.3g} GiB (> --max-memory-gib "
            f"{options.max_memory_gib:g}): use a coarser or smaller grid (--grid, --voxel-um), drop --tv, or use rl/fista"
        )


def _background(measurement: np.ndarray, background: str | float) -> float:
    if background == "auto":
        return float(np.median(measurement))
    if background == "none":
        return 0.0
    return float(background)


def _checked_measurement(measurement: Any, operator: VolumeOperator) -> np.ndarray:
    """The measurement as a float32 image; a ValueError unless it is one finite image of the sensor's shape."""
    measurement = np.asarray(measurement, dtype=np.float32)
    if measurement.ndim != 2:
        raise ValueError(f"a measurement must be one image (y, x), got shape {measurement.shape}")
    if tuple(measurement.shape) != tuple(operator.sensor_shape):
        raise ValueError(
            f"the measurement is {measurement.shape[0]} × {measurement.shape[1]} px, the model's sensor "
            f"{operator.sensor_shape[0]} × {operator.sensor_shape[1]} px"
        )
    if not np.all(np.isfinite(measurement)):
        raise ValueError(f"the measurement contains {int(np.sum(~np.isfinite(measurement)))} NaN or infinite pixels")
    return measurement


def _solve(
    operator: VolumeOperator, b: torch.Tensor, options: ReconOptions, background: float, progress: Progress | None
) -> tuple[SolverResult, str]:
    """Run the options' method on the scaled measurement ``b`` (``background`` in b's units, for
    rl); returns the result and the variant that ran."""
    stopping = options.stopping
    result: SolverResult
    variant = options.method
    if options.method == "fista":
        result = fista(
            operator,
            b,
            l1=options.l1,
            tv=options.tv,
            stopping=stopping,
            tv_iterations=options.tv_iterations,
            progress=progress,
        )
    elif options.method == "admm" and isinstance(operator, DepthwiseConvOperator):
        variant = "admm-lsi (closed form)"
        result = admm_lsi(
            operator,
            b,
            l1=options.l1,
            tv=options.tv,
            mu=(1.0, options.mu, options.mu),
            stopping=stopping,
            progress=progress,
        )
    elif options.method == "admm":
        variant = "admm (CG x-update)"
        result = admm(
            operator,
            b,
            l1=options.l1,
            tv=options.tv,
            mu=options.mu,
            cg_iterations=options.cg_iterations,
            stopping=stopping,
            progress=progress,
        )
    else:
        result = richardson_lucy(
            operator,
            b,
            background=background,
            l1=options.l1,
            tv=options.tv,
            stopping=stopping,
            progress=progress,
        )
    return result, variant


def reconstruct(
    measurement: np.ndarray,
    operator: VolumeOperator,
    options: ReconOptions = ReconOptions(),
    *,
    progress: Progress | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Reconstruct ``measurement`` (y, x) with ``operator``; returns the (z, y, x) float32 volume
    and a record (options, background, scale, iterations, convergence, memory, seconds)."""
    measurement = _checked_measurement(measurement, operator)
    memory = memory_estimate(operator, options)
    if memory["total_gib"] > options.max_memory_gib:
        raise ValueError(
            f"{options.method} on a {'×'.join(map(str, operator.grid.shape))} grid needs ≈ {memory['total_gib']:.1f} GiB "
            f"(> --max-memory-gib {options.max_memory_gib:g}): use a coarser or smaller grid, drop --tv, or use rl/fista"
        )
    start = time.perf_counter()
    background = _background(measurement, options.background)
    signal = measurement - background
    scale = float(signal.max())
    if not scale > 0:
        raise ValueError("the measurement has no signal above its background")
    b = torch.as_tensor(measurement / scale if options.method == "rl" else signal / scale)
    result, variant = _solve(operator, b, options, background / scale, progress)
    volume = (result.volume * scale).cpu().numpy().astype(np.float32)
    record = {
        "method": options.method,
        "variant": variant,
        "options": asdict(options),
        "background": background,
        "scale": scale,
        "iterations": result.iterations,
        "converged": result.converged,
        "final_rel_change": result.history["rel_change"][-1] if result.history.get("rel_change") else None,
        "final_residual": _finite(result.history.get("residual", [])),
        "lipschitz": result.lipschitz,
        "memory_estimate": {k: round(v, 4) if isinstance(v, float) else v for k, v in memory.items()},
        "seconds": round(time.perf_counter() - start, 3),
        "grid": operator.grid.to_dict(),
    }
    return volume, record


def _finite(values: list[float]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return finite[-1] if finite else None


def reconstruct_file(
    measurement_path: str | Path,
    model_path: str | Path,
    out_path: str | Path,
    options,
    *,
    forward: str = "lsv",
    grid=None,
    dark_level: float = 0.0,
    progress=None,
    device: str = "cpu",
) -> dict:
    """Read, reconstruct, write the volume (TIFF/.npy) and ``<out>.json`` beside it; returns the
    record. device: where the operator and the solver's arrays live (``cpu``, ``cuda:N``)."""
    from cm2optics.formats.atomic import write_json_atomic
    from cm2optics.formats.measurement import read_measurement
    from cm2optics.formats.models import model_grid
    from cm2optics.formats.volume import write_volume
    from cm2optics.recon.operators import load_operator

    out_path = Path(out_path)
    if out_path.suffix.lower() not in (".tif", ".tiff", ".npy"):
        raise UserError(f"--out {out_path}: give a .tif or .npy file name")
    check_memory(grid or model_grid(model_path), options)  # before anything is read or allocated
    measurement = read_measurement(measurement_path, dark_level)
    operator = load_operator(model_path, grid, forward=forward, device=device)
    volume, record = reconstruct(measurement, operator, options, progress=progress)
    write_volume(out_path, volume, operator.grid.voxel_um)
    record.update(
        {
            "measurement": str(measurement_path),
            "model": str(model_path),
            "forward": forward,
            "volume": str(out_path),
            "device": str(device),
        }
    )
    write_json_atomic(out_path.with_suffix(".json"), record)
    return record


def check_device(device: str) -> None:
    """A UserError unless ``device`` names the CPU or a CUDA device this machine has."""
    try:
        parsed = torch.device(device)
    except RuntimeError:
        raise UserError(f"--device {device}: give cpu or cuda[:N]") from None
    if parsed.type not in ("cpu", "cuda"):
        raise UserError(f"--device {device}: give cpu or cuda[:N]")
    if parsed.type == "cuda":
        count = torch.cuda.device_count()
        if count == 0:
            raise UserError(f"--device {device}: no CUDA device on this machine")
        if parsed.index is not None and parsed.index >= count:
            raise UserError(f"--device {device}: this machine has {count} CUDA device(s)")
