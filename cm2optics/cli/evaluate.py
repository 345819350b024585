"""``cm2 evaluate RECON GT``: detection and localisation metrics of a reconstruction.

Registered by :mod:`cm2optics.cli`; the work is :func:`cm2optics.metrics.evaluate.evaluate_files`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from cm2optics.cli.options import JsonOption, OverwriteOption, check_output, parse_float_list, parse_names, user_errors

__all__ = ["evaluate_command"]


@user_errors
def evaluate_command(
    recon: Annotated[Path, typer.Argument(help="Reconstructed volume: TIFF (z, y, x) with ImageJ spacing, or .npy.")],
    ground_truth: Annotated[
        Path,
        typer.Argument(
            metavar="GT",
            help="Ground truth: an emitter CSV (x_um,y_um,z_um,diameter_um,intensity) or a volume on the same grid.",
        ),
    ],
    threshold: Annotated[
        float | None,
        typer.Option(
            "--threshold",
            "-t",
            help="Global threshold that binarises RECON (its units); default: the F1-optimal one on this pair.",
        ),
    ] = None,
    validation: Annotated[
        list[str] | None,
        typer.Option(
            "--validation",
            help="A validation pair RECON,GT (repeatable): without --threshold, the F1-optimal threshold on these.",
        ),
    ] = None,
    gate_factor: Annotated[
        float,
        typer.Option("--gate-factor", help="A detection matches a true emitter within this × its diameter (paper: 2)."),
    ] = 2.0,
    min_gate_um: Annotated[
        float | None,
        typer.Option("--min-gate-um", help="Floor of the matching gate, µm; default: the coarsest voxel pitch."),
    ] = None,
    connectivity: Annotated[
        int, typer.Option("--connectivity", help="Connected components: 6, 18 or 26 neighbours.")
    ] = 26,
    voxel_um: Annotated[
        str | None,
        typer.Option("--voxel-um", help="Voxel pitch z,y,x in µm (needed for .npy; overrides TIFF metadata)."),
    ] = None,
    patch_um: Annotated[float, typer.Option("--patch-um", help="Patch side of the recall/precision maps, µm.")] = 250.0,
    out_dir: Annotated[
        Path | None,
        typer.Option("--out", "-o", help="Folder for metrics.json and the figures (breakdowns, maps, overlay)."),
    ] = None,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Recall, precision, F1, Jaccard and lateral/axial RMSE of RECON against GT.

    RECON is binarised at one global threshold, its connected components are the detections
    (value-weighted centroids), and they are matched to the true emitters by the Hungarian
    algorithm, a pair allowed only within --gate-factor × the true diameter (3-D distance in µm).
    Breakdowns by distance from the centre, depth and size (the paper's Fig. 6 bins) and
    recall/precision maps are included in the JSON and drawn with --out.
    """
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    from cm2optics.formats.outputs import claim_folder
    from cm2optics.metrics.evaluate import evaluate_files
    from cm2optics.metrics.scores import REPORTED_KEYS, MatchOptions

    pairs = [parse_names(v, name="--validation", n=2, what="file names RECON,GT") for v in validation or ()]
    voxel = parse_float_list(voxel_um, 3, name="--voxel-um", low=0, low_open=True, example="10,4.15,4.15")
    if out_dir is not None:
        inputs = [recon, ground_truth, *(p for pair in pairs for p in pair)]
        check_output(out_dir, command="evaluate", kind="folder", inputs=inputs, overwrite=overwrite)
    options = MatchOptions(gate_factor=gate_factor, min_gate_um=min_gate_um, connectivity=connectivity)
    with Progress(disable=as_json, transient=True, console=Console(stderr=True)) as bar:
        task = bar.add_task("threshold sweep", total=None if threshold is None else 1)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        result = evaluate_files(
            recon,
            ground_truth,
            threshold=threshold,
            options=options,
            voxel_um=voxel,
            patch_um=patch_um,
            out_dir=out_dir,
            plots=out_dir is not None,
            validation=[tuple(pair) for pair in pairs] or None,
            progress=progress,
        )
    if out_dir is not None:
        claim_folder(out_dir, "evaluate")
    if as_json:
        print(json.dumps(result, indent=2, ensure_ascii=False))
        return
    console = Console()
    table = Table(
        title=f"{recon.name} against {ground_truth.name} (threshold {result['threshold']:.4g}, {result['threshold_source']})"
    )
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key in REPORTED_KEYS:
        value = result[key]
        table.add_row(key, "—" if value is None else (f"{value:.4f}" if isinstance(value, float) else str(value)))
    console.print(table)
    if out_dir is not None:
        console.print(f"[green]written[/]: {Path(out_dir) / 'metrics.json'} and figures")
