"""``cm2 synth``: a synthetic training/test set made the paper's way from a forward model.

Registered by :mod:`cm2optics.cli`; the work is :func:`cm2optics.synth.dataset.make_dataset`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from cm2optics.cli.options import (
    JsonOption,
    OverwriteOption,
    check_dask_address,
    output_folder,
    parse_float_list,
    user_errors,
)
from cm2optics.errors import UserError

__all__ = ["synth_command"]


@user_errors
def synth_command(
    model: Annotated[
        Path, typer.Option("--model", "-m", help="Forward model: an LSV model (cm2 lsv build) or a PSF stack (HDF5).")
    ],
    out_dir: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for manifest.json, dataset.h5 and samples/.")
    ] = Path("out/synth"),
    n_volumes: Annotated[int, typer.Option("--n-volumes", "-n", help="Number of volumes (samples).")] = 20,
    seed: Annotated[int, typer.Option("--seed", help="Data-set seed: the same seed gives the same data.")] = 0,
    preset: Annotated[
        str, typer.Option("--size", help="paper (full size) or scaled (field, views and patches ÷ --scale).")
    ] = "paper",
    scale: Annotated[float, typer.Option("--scale", help="Shrink factor of --size scaled.")] = 4.0,
    config_file: Annotated[
        Path | None,
        typer.Option("--config", help="JSON/YAML of SynthConfig fields (applied before the options below)."),
    ] = None,
    fov_mm: Annotated[str | None, typer.Option("--fov-mm", help="Field of view low,high, mm (paper: 6.5,7.5).")] = None,
    depth_um: Annotated[float | None, typer.Option("--depth-um", help="Depth range, µm (paper: 800).")] = None,
    voxel_um: Annotated[
        str | None, typer.Option("--voxel-um", help="Voxel z,y,x in µm (default: the model's grid pitch).")
    ] = None,
    diameter_um: Annotated[
        str | None, typer.Option("--diameter-um", help="Emitter diameter low,high, µm (paper: 8,20).")
    ] = None,
    density: Annotated[str | None, typer.Option("--density", help="Emitters per mm² low,high (paper: 10,100).")] = None,
    noise: Annotated[
        str | None, typer.Option("--noise", help="poisson-gaussian (paper), variance (a·I + b) or none.")
    ] = None,
    render: Annotated[
        str | None, typer.Option("--render", help="auto, sparse (emitters straight from the model) or volume.")
    ] = None,
    view_px: Annotated[
        int | None, typer.Option("--view-px", help="Side of the nine cropped views, px (paper: 1920; 0: none).")
    ] = None,
    patch_px: Annotated[
        int | None, typer.Option("--patch-px", help="Side of the training patches, px (paper: 320; 0: none).")
    ] = None,
    patches: Annotated[int | None, typer.Option("--patches", help="Patches per volume.")] = None,
    store_volume: Annotated[
        bool | None, typer.Option("--volume/--no-volume", help="Keep each ground-truth volume.")
    ] = None,
    workers: Annotated[int, typer.Option("--workers", help="Local Dask workers (0: in this process).")] = 2,
    dask_address: Annotated[
        str | None,
        typer.Option("--dask-address", help="An existing Dask scheduler (tcp://host:8786); default: a local cluster."),
    ] = None,
    export: Annotated[
        int,
        typer.Option("--export", help="Also write the first N samples as TIFF/CSV (for cm2 reconstruct / evaluate)."),
    ] = 0,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Synthesise volumes of spherical emitters, their noisy measurements through the model,
    the ground-truth demixed views, the nine views cropped at the chief rays and training patches.

    The paper's recipe (Section 2.4): field U[6.5, 7.5] mm, 800 µm deep, 4.15 × 4.15 × 10 µm
    voxels, balls drawn on a 5× finer grid and averaged down, diameter U[8, 20] µm, intensity
    ∝ diameter² × U[0.8, 1.2], density U[10, 100] per mm², Poisson (≈ 500 peak photons) plus
    Gaussian noise (mean 0.048, sd 0.017). Volumes are made in parallel on Dask.
    """
    from rich.console import Console
    from rich.progress import Progress

    from cm2optics.formats.models import model_grid
    from cm2optics.synth.config import SynthConfig
    from cm2optics.synth.dataset import make_dataset
    from cm2optics.formats.outputs import output_lock
    from cm2optics.synth.files import export_sample, read_config_file

    if preset not in ("paper", "scaled"):
        raise UserError(f"--size = {preset!r}: must be paper or scaled")
    if n_volumes < 1 or export < 0:
        raise UserError(f"--n-volumes = {n_volumes} must be ≥ 1 and --export = {export} ≥ 0")
    pair = {"n": 2, "repeat_single": True, "low": 0, "example": "6.5,7.5"}
    given = (("--fov-mm", fov_mm), ("--diameter-um", diameter_um), ("--density", density))
    ranges = {name: parse_float_list(text, name=name, **pair) for name, text in given}
    voxel_given = parse_float_list(voxel_um, 3, name="--voxel-um", low=0, low_open=True, example="10,4.15,4.15")
    grid = model_grid(model)
    voxel = voxel_given or (grid.voxel_um if grid is not None else None)
    base = SynthConfig.paper() if preset == "paper" else SynthConfig.scaled(scale)
    values: dict[str, Any] = base.to_dict()
    if voxel is not None:
        values["voxel_um"] = list(voxel)
    if config_file is not None:
        values.update(read_config_file(config_file))
    overrides = {
        "fov_mm": ranges["--fov-mm"],
        "depth_um": depth_um,
        "voxel_um": voxel_given,
        "diameter_um": ranges["--diameter-um"],
        "density_per_mm2": ranges["--density"],
        "noise": noise,
        "render": render,
        "view_px": view_px,
        "patch_px": patch_px,
        "patches_per_volume": patches,
        "store_volume": store_volume,
    }
    values.update({k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items() if v is not None})
    config = SynthConfig.from_dict(values)
    check_dask_address(dask_address)
    output_folder(out_dir, "synth", inputs=[model, config_file], overwrite=overwrite)
    with output_lock(out_dir, "synth"), Progress(disable=as_json, transient=True, console=Console(stderr=True)) as bar:
        task = bar.add_task("synthesising volumes", total=n_volumes)
        manifest = make_dataset(
            config,
            model,
            out_dir,
            n_volumes,
            seed,
            dask_address=dask_address,
            workers=workers,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )
    if export:
        manifest["exported"] = [
            export_sample(out_dir / "samples" / s["file"], out_dir / "export") for s in manifest["samples"][:export]
        ]
    if as_json:
        print(
            json.dumps(
                {k: v for k, v in manifest.items() if k != "samples"} | {"samples": manifest["samples"]},
                indent=2,
                ensure_ascii=False,
            )
        )
        return
    console = Console()
    grid = config.grid
    console.print(
        f"[green]{n_volumes} volumes[/] ({'×'.join(map(str, grid.shape))} voxels of {'×'.join(f'{v:g}' for v in grid.voxel_um)} µm, "
        f"{manifest['n_emitters']} emitters, {manifest['n_patches']} patches) in {manifest['seconds']:.1f} s → {out_dir}"
    )
