"""``cm2 reconstruct MEAS.tif --model MODEL --method fista|admm|rl --out VOL.tif`` and
``cm2 reconstruct MEAS.tif --method net --weights reconstruction/NAME [--out VOL.tif] [--emitters-out E.csv]``.

Registered by :mod:`cm2optics.cli`; the work is :func:`cm2optics.recon.reconstruct.reconstruct_file`
(model-based) or :func:`cm2optics.recon.net.infer.reconstruct_net_file` (CM²Net).
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
        Path | None,
        typer.Option(
            "--model",
            "-m",
            help="Forward model: an LSV model (cm2 lsv build) or a PSF stack. Required for fista, admm and rl; "
            "with --method net it gives the chief rays and refocusing geometry (default: the model the weights "
            "were trained through).",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            "-o",
            help="Reconstructed volume (.tif with ImageJ spacing, or .npy); a .json record beside it "
            "(default: MEAS's name with .volume.tif, beside it).",
        ),
    ] = None,
    method: Annotated[
        str, typer.Option("--method", help="fista, admm or rl (model-based), or net (CM²Net, with --weights).")
    ] = "fista",
    weights: Annotated[
        Path | None,
        typer.Option("--weights", help="--method net: a weights folder, e.g. reconstruction/cm2net-cpu."),
    ] = None,
    emitters_out: Annotated[
        Path | None,
        typer.Option("--emitters-out", help="--method net: also write the detected emitters here (CSV, µm)."),
    ] = None,
    preprocess: Annotated[
        str,
        typer.Option(
            "--preprocess",
            help="--method net: histogram (match the training views' histogram: measured frames, the paper's way), "
            "max (divide by the maximum) or none (a measurement simulated like the training data).",
        ),
    ] = "histogram",
    threshold: Annotated[
        float | None,
        typer.Option("--threshold", help="--method net: detection threshold on [0, 1] (default: the weights')."),
    ] = None,
    field_mm: Annotated[
        float | None,
        typer.Option(
            "--field-mm",
            help="--method net: reconstruct a disc of this diameter, mm (views that hold it; e.g. 7 for the whole "
            "field of a full-sensor frame with a model of the whole sensor); default: the training views' field.",
        ),
    ] = None,
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
    device: Annotated[
        str,
        typer.Option(
            "--device", help="fista, admm, rl: where the operator and the solver run, cpu or cuda[:N] (a GPU)."
        ),
    ] = "cpu",
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Reconstruct a volume from one frame: model-based (FISTA, ADMM or Richardson–Lucy with
    non-negativity, ℓ1 and 3-D TV; with --forward lsi and --method admm the V1 paper's depth-wise
    LSI ADMM) or with trained CM²Net weights (--method net --weights DIR: one pass, seconds).

    Examples:
      cm2 reconstruct meas.tif --model model.h5 --method fista --out vol.tif
      cm2 reconstruct meas.tif --method net --weights reconstruction/cm2net-cpu --emitters-out found.csv"""
    from rich.console import Console

    from cm2optics.recon.reconstruct import ReconOptions, reconstruct_file

    if out is None:
        out = measurement.with_name(measurement.stem + ".volume.tif")
    if method == "net":
        if device != "cpu":
            raise UserError("--device goes with fista, admm and rl (--method net runs on the CPU)")
        _reconstruct_net(
            measurement,
            model,
            out,
            weights,
            emitters_out,
            preprocess,
            threshold,
            field_mm,
            dark_level,
            overwrite,
            as_json,
        )
        return
    if weights is not None or emitters_out is not None or field_mm is not None:
        raise UserError("--weights, --emitters-out and --field-mm go with --method net")
    from cm2optics.recon.reconstruct import check_device

    check_device(device)
    if model is None:
        raise UserError(f"--method {method}: give the forward model with --model (an LSV model or a PSF stack)")
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
            measurement,
            model,
            out,
            options,
            forward=forward,
            grid=grid,
            dark_level=dark_level,
            progress=progress,
            device=device,
        )
    if as_json:
        print(json.dumps(record, indent=2, ensure_ascii=False))
        return
    state = "converged" if record["converged"] else "stopped at the iteration cap"
    Console().print(
        f"[green]{out}[/]: {record['variant']}, {record['iterations']} iterations ({state}), {record['seconds']:.1f} s"
    )


def _reconstruct_net(
    measurement: Path,
    model: Path | None,
    out: Path,
    weights: Path | None,
    emitters_out: Path | None,
    preprocess: str,
    threshold: float | None,
    field_mm: float | None,
    dark_level: float,
    overwrite: bool,
    as_json: bool,
) -> None:
    """``--method net``: check the options and outputs, run CM²Net, print the record."""
    from rich.console import Console

    from cm2optics.recon.net.infer import PREPROCESS, reconstruct_net_file

    if weights is None:
        raise UserError("--method net needs --weights (a weights folder, e.g. reconstruction/cm2net-cpu)")
    if preprocess not in PREPROCESS:
        raise UserError(f"--preprocess {preprocess}: must be one of {', '.join(PREPROCESS)}")
    if threshold is not None and not 0.0 < threshold < 1.0:
        raise UserError(f"--threshold {threshold}: must lie strictly between 0 and 1")
    if field_mm is not None and not 0.0 < field_mm <= 100.0:
        raise UserError(f"--field-mm {field_mm}: must lie in (0, 100] mm")
    inputs = [p for p in (measurement, model, weights) if p is not None]
    outputs = [out, out.with_suffix(".json")] + ([emitters_out] if emitters_out is not None else [])
    for path in outputs:
        check_output(path, command="reconstruct", inputs=inputs, overwrite=overwrite)
    record = reconstruct_net_file(
        measurement,
        weights,
        out,
        model=model,
        emitters_out=emitters_out,
        preprocess=preprocess,
        threshold=threshold,
        dark_level=dark_level,
        field_mm=field_mm,
    )
    if as_json:
        print(json.dumps(record, indent=2, ensure_ascii=False))
        return
    Console().print(
        f"[green]{out}[/]: CM²Net, {record['n_emitters']} emitters at threshold {record['threshold']:g}, "
        f"{record['seconds']['total']:.1f} s"
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
