"""``cm2 reconstruct MEAS.tif --model MODEL --method fista|admm|rl --out VOL.tif``.

Registered by :mod:`cm2optics.cli`; the work is :func:`cm2optics.recon.reconstruct.reconstruct_file`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from cm2optics.cli.options import (
    JsonOption,
    OverwriteOption,
    check_output,
    parse_float_list,
    parse_int_list,
    user_errors,
)
from cm2optics.errors import UserError

__all__ = ["reconstruct_command"]


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
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Model-based reconstruction: FISTA, ADMM or Richardson–Lucy with non-negativity, ℓ1 and
    3-D TV. With --forward lsi and --method admm this is the V1 paper's depth-wise LSI ADMM."""
    from rich.console import Console

    from cm2optics.recon.reconstruct import ReconOptions, reconstruct_file

    for path in (out, out.with_suffix(".json")):
        check_output(path, command="reconstruct", inputs=[measurement, model], overwrite=overwrite)
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
    grid = _grid_option(grid_shape, voxel_um)
    with _iteration_bar(quiet=as_json) as bar:
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


def _grid_option(grid_shape: str | None, voxel_um: str | None) -> Any:
    """The VolumeGrid of --grid z,y,x and --voxel-um z,y,x (µm), given together; None when neither is."""
    from cm2optics.formats.volume import VolumeGrid

    if grid_shape is None and voxel_um is None:
        return None
    shape = parse_int_list(grid_shape, 3, name="--grid", low=1, example="101,480,480")
    voxel = parse_float_list(voxel_um, 3, name="--voxel-um", low=0, low_open=True, example="10,4.15,4.15")
    if shape is None or voxel is None:
        raise UserError("--grid and --voxel-um go together")
    return VolumeGrid(shape, voxel)


def _iteration_bar(*, quiet: bool) -> Any:
    """A transient progress bar on stderr with the iteration count and the relative change Δ."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} Δ={task.fields[change]}"),
        TimeElapsedColumn(),
    )
    return Progress(*columns, disable=quiet, transient=True, console=Console(stderr=True))
