"""``cm2 reconstruct MEAS.tif --model MODEL --method fista|admm|rl --out VOL.tif``.

The lead registers it on the top-level app: ``app.command("reconstruct")(reconstruct_command)``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from cm2optics.cli.options import JsonOption, user_errors
from cm2optics.cli.evaluate import parse_triple

__all__ = ["read_measurement", "reconstruct_command", "reconstruct_file"]


def read_measurement(path: str | Path, dark_level: float = 0.0):
    """A measurement image (TIFF or .npy) as float32 (y, x), less ``dark_level``."""
    import numpy as np
    import tifffile

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such measurement file")
    try:
        if path.suffix.lower() == ".npy":
            data = np.load(path, allow_pickle=False)
        elif path.suffix.lower() in (".tif", ".tiff"):
            data = tifffile.imread(path)
        else:
            raise ValueError(f"{path}: unknown measurement format {path.suffix!r} (use .tif or .npy)")
    except ValueError:
        raise
    except Exception as error:  # tifffile/numpy raise many types for corrupt files
        raise ValueError(f"{path}: not a readable image ({error})") from None
    data = np.squeeze(np.asarray(data))
    if data.ndim != 2:
        raise ValueError(f"{path}: a measurement is one image (y, x), found shape {data.shape}")
    if not np.issubdtype(data.dtype, np.number) or np.iscomplexobj(data):
        raise ValueError(f"{path}: pixel values must be real numbers (found {data.dtype})")
    data = data.astype(np.float32) - np.float32(dark_level)
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{path}: contains {int(np.sum(~np.isfinite(data)))} NaN or infinite pixels")
    return data


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
) -> dict:
    """Read, reconstruct, write the volume (TIFF/.npy) and ``<out>.json`` beside it; returns the record."""
    from cm2optics.io import write_json_atomic
    from cm2optics.recon.operators import load_operator
    from cm2optics.recon.reconstruct import reconstruct
    from cm2optics.volume_io import write_volume

    out_path = Path(out_path)
    if out_path.suffix.lower() not in (".tif", ".tiff", ".npy"):
        raise ValueError(f"--out {out_path}: give a .tif or .npy file name")
    measurement = read_measurement(measurement_path, dark_level)
    operator = load_operator(model_path, grid, forward=forward)
    volume, record = reconstruct(measurement, operator, options, progress=progress)
    write_volume(out_path, volume, operator.grid.voxel_um)
    record.update(
        {"measurement": str(measurement_path), "model": str(model_path), "forward": forward, "volume": str(out_path)}
    )
    write_json_atomic(out_path.with_suffix(".json"), record)
    return record


@user_errors
def reconstruct_command(
    measurement: Annotated[
        Path, typer.Argument(metavar="MEAS", help="Measurement: one image (TIFF or .npy), e.g. a raw 16-bit frame.")
    ],
    model: Annotated[
        Path, typer.Option("--model", "-m", help="Forward model: an LSV model (cm2 lsv build) or a PSF stack.")
    ],
    out: Annotated[
        Path,
        typer.Option(
            "--out", "-o", help="Reconstructed volume (.tif with ImageJ spacing, or .npy); a .json record beside it."
        ),
    ],
    method: Annotated[str, typer.Option("--method", help="fista, admm or rl.")] = "fista",
    forward: Annotated[
        str,
        typer.Option("--forward", help="lsv (the 3D-LSV model) or lsi (the V1 depth-wise LSI model derived from it)."),
    ] = "lsv",
    l1: Annotated[float, typer.Option("--l1", help="ℓ1 weight relative to ‖Aᵀb‖∞ (RL: to mean Aᵀ1).")] = 0.02,
    tv: Annotated[float, typer.Option("--tv", help="3-D TV weight, relative like --l1.")] = 0.0,
    iterations: Annotated[int, typer.Option("--iterations", help="Iteration cap.")] = 100,
    tol: Annotated[float, typer.Option("--tol", help="Stop when the relative change stays below this ...")] = 1e-3,
    patience: Annotated[int, typer.Option("--patience", help="... for this many consecutive iterations.")] = 3,
    background: Annotated[
        str, typer.Option("--background", help="auto (image median), none, or a value in the measurement's units.")
    ] = "auto",
    dark_level: Annotated[
        float, typer.Option("--dark-level", help="Subtracted from every pixel first (raw frames).")
    ] = 0.0,
    grid_shape: Annotated[
        str | None, typer.Option("--grid", help="Volume shape z,y,x (default: the model's grid).")
    ] = None,
    voxel_um: Annotated[str | None, typer.Option("--voxel-um", help="Voxel z,y,x in µm, with --grid.")] = None,
    max_memory_gib: Annotated[
        float, typer.Option("--max-memory-gib", help="Refuse a run estimated above this.")
    ] = 20.0,
    as_json: JsonOption = False,
) -> None:
    """Model-based reconstruction: FISTA, ADMM or Richardson–Lucy with non-negativity, ℓ1 and
    3-D TV. With --forward lsi and --method admm this is the V1 paper's depth-wise LSI ADMM."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from cm2optics.recon.reconstruct import ReconOptions
    from cm2optics.volume_io import VolumeGrid

    options = ReconOptions(
        method=method,
        l1=l1,
        tv=tv,
        max_iter=iterations,
        tol=tol,
        patience=patience,
        background=background,
        max_memory_gib=max_memory_gib,
    )
    grid = None
    if grid_shape is not None or voxel_um is not None:
        shape = parse_triple(grid_shape, "--grid")
        voxel = parse_triple(voxel_um, "--voxel-um")
        if shape is None or voxel is None:
            raise ValueError("--grid and --voxel-um go together")
        grid = VolumeGrid(tuple(int(v) for v in shape), voxel)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} Δ={task.fields[change]}"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, disable=as_json, transient=True, console=Console(stderr=True)) as bar:
        task = bar.add_task(f"{method} ({forward})", total=iterations, change="–")

        def progress(k: int, total: int, info: dict) -> None:
            bar.update(task, completed=k, change=f"{info.get('rel_change', float('nan')):.2e}")

        record = reconstruct_file(
            measurement, model, out, options, forward=forward, grid=grid, dark_level=dark_level, progress=progress
        )
    if as_json:
        print(json.dumps(record, indent=2, ensure_ascii=False))
        return
    state = "converged" if record["converged"] else "stopped at the iteration cap"
    Console().print(
        f"[green]{out}[/]: {record['variant']}, {record['iterations']} iterations ({state}), {record['seconds']:.1f} s"
    )
