"""``cm2 demo`` and ``cm2 compare-baselines``: whole-pipeline runs that write a report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from cm2optics.cli.options import (
    OverwriteOption,
    PresetOption,
    check_dask_address,
    check_output,
    output_folder,
    user_errors,
)

__all__ = ["compare_baselines_command", "demo_command"]

out = Console()


@user_errors
def demo_command(
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Folder for the report and its figures.")] = Path(
        "out/demo"
    ),
    preset: PresetOption = "cm2-v2",
    analytic: Annotated[
        bool,
        typer.Option(
            "--analytic",
            help="Build the 3D-LSV model of sections 6–7 from a closed-form CM²-like scan (the fast fallback, "
            "about two minutes sooner) instead of the traced calibration scan of section 5.",
        ),
    ] = False,
    weights: Annotated[
        Path | None,
        typer.Option(
            "--weights",
            help="CM²Net weights folder for section 8 (default: the repository's reconstruction/cm2net-cpu).",
        ),
    ] = None,
    overwrite: OverwriteOption = False,
) -> None:
    """Run every stage built so far at demo size and write `report.html` and `report.md`.

    One chain: the design's parts, spectra and illumination; a traced PSF calibration scan; the
    3D-LSV model built from that scan; a synthetic volume simulated through it, reconstructed
    and scored; CM²Net with the shipped weights beside FISTA."""
    from cm2optics.design import load_preset
    from cm2optics.errors import UserError
    from cm2optics.reports.demo import run_demo

    if weights is not None and not weights.is_dir():
        raise UserError(f"--weights {weights}: no such weights folder")
    design = load_preset(preset)
    output_folder(out_dir, "demo", inputs=[preset, weights], overwrite=overwrite)
    report = run_demo(design, out_dir, analytic=analytic, weights=weights)
    out.print(f"[green]demo report:[/] {report}")


@user_errors
def compare_baselines_command(
    model: Annotated[
        Path, typer.Argument(help="LSV model (cm2 lsv build); if absent, an analytic one is built there first.")
    ],
    out_dir: Annotated[Path, typer.Argument(metavar="OUT", help="Folder for comparison.json/.md and the figures.")],
    n_volumes: Annotated[int, typer.Option("--n-volumes", help="Test volumes.")] = 20,
    factor: Annotated[float, typer.Option("--factor", help="Field ÷ factor (the scaled-down equivalent).")] = 2.0,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the test set.")] = 2024,
    threads: Annotated[int, typer.Option("--threads", help="Torch threads per reconstruction.")] = 1,
    workers: Annotated[int, typer.Option("--workers", help="Local Dask workers making the test set.")] = 2,
    runs: Annotated[str | None, typer.Option("--runs", help="JSON of runs (default: lsv-fista and lsi-admm).")] = None,
    build_binning: Annotated[
        int, typer.Option("--build-binning", help="If MODEL does not exist: build an analytic one at this binning.")
    ] = 4,
    reuse: Annotated[
        bool, typer.Option("--reuse", help="Reuse runs already reconstructed in OUT (same options and samples).")
    ] = False,
    dask_address: Annotated[
        str | None, typer.Option("--dask-address", help="An existing Dask scheduler (tcp://host:8786).")
    ] = None,
    overwrite: OverwriteOption = False,
) -> None:
    """LSV against LSI model-based reconstruction on a synthetic test set (the BENCHMARKS.md run).

    Makes --n-volumes scaled-down test volumes through MODEL, reconstructs each with every run
    (default: LSV FISTA and the V1 paper's depth-wise LSI ADMM), evaluates them at each run's
    F1-optimal threshold and writes comparison.json, comparison.md and figures into OUT.
    """
    from cm2optics.design import load_preset
    from cm2optics.errors import UserError
    from cm2optics.lsv.model import load_model
    from cm2optics.lsv.toy import analytic_lsv_model_file
    from cm2optics.recon.compare import compare_baselines, scaled_test_config

    if n_volumes < 1 or factor <= 0 or threads < 1 or workers < 0:
        raise UserError("--n-volumes and --threads must be ≥ 1, --factor > 0, --workers ≥ 0")
    try:
        run_table = json.loads(runs) if runs else None
    except ValueError as error:
        raise UserError(f"--runs: not valid JSON ({error})") from None
    check_dask_address(dask_address)
    output_folder(out_dir, "compare-baselines", inputs=[model], overwrite=overwrite)
    if not model.is_file():
        check_output(model, command="compare-baselines", option="MODEL")
        analytic_lsv_model_file(model, load_preset("cm2-v2"), binning=build_binning)
    config = scaled_test_config(load_model(model), factor)
    compare_baselines(
        model,
        out_dir,
        n_volumes=n_volumes,
        seed=seed,
        config=config,
        runs=run_table,
        threads=threads,
        workers=workers,
        dask_address=dask_address,
        reuse=reuse,
    )
