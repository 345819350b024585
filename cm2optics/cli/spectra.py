"""``cm2 spectra``: the spectral report of a design, and the filter fitter.

Registered by :mod:`cm2optics.cli`; the work is :func:`cm2optics.reports.spectra.spectra_report` and
:func:`cm2optics.spectra.fit.fit_filter_models`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from cm2optics.cli.options import JsonOption, OverwriteOption, PresetOption, check_output, parse_float_list, user_errors
from cm2optics.errors import UserError
from cm2optics.optics.checks import check_design
from cm2optics.spectra.library import egfp_emission_band_nm

__all__ = ["spectra_app"]

spectra_app = typer.Typer(
    help="Spectra and filters of the emission path: the hybrid filter's signal-to-background ratio (SBR), "
    "and a fitter for vendors' angle-resolved filter curves.",
    no_args_is_help=True,
)

_out = Console()


@spectra_app.command("report")
@user_errors
def report(
    preset: PresetOption = "cm2-v2",
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Folder for the PNG plots.")] = Path("out/spectra"),
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """SBR of the emission path, interference-only vs hybrid (interference filter + absorption film).

    Traces fluorescence from the imaged field and excitation light (scattered by the sample where the
    LED beams land, and reflected by its surface) through the filter, mask and lenslets to the sensor,
    each ray at its own angle of incidence (degrees at the filter). Writes filter_vs_angle.png
    (transmission at 0/20/40/60°), chain.png and sbr_vs_angle.png into --out. JSON keys include
    sbr_interference_only, sbr_hybrid, sbr_gain, per-angle figures and the film sensitivity.
    """
    from cm2optics.design import load_preset
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.reports.spectra import spectra_report

    design = load_preset(preset)
    for problem in check_design(design, egfp_emission_band_nm()):
        typer.echo(f"warning: the SBR is implausible for this design: {problem}", err=True)
    check_output(out_dir, command="spectra report", kind="folder", inputs=[preset], overwrite=overwrite)
    figures = spectra_report(design, out_dir)
    claim_folder(out_dir, "spectra report")
    if as_json:
        print(json.dumps(figures, indent=2, ensure_ascii=False))
        return
    table = Table(title=f"{design.name}: emission path, per photon the LEDs emit (photoelectrons over the sensor)")
    for column in ("chain", "signal", "background", "SBR"):
        table.add_column(column, justify="right")
    for chain in ("interference_only", "hybrid"):
        table.add_row(
            chain.replace("_", " "),
            f"{figures['signal_per_excitation_photon'][chain]:.3g}",
            f"{figures['background_per_excitation_photon'][chain]:.3g}",
            f"{figures[f'sbr_{chain}']:.3g}",
        )
    _out.print(table)
    _out.print(
        f"SBR gain of the hybrid filter: [bold]{figures['sbr_gain']:.3g}×[/] "
        f"(signal kept {figures['signal_transmission_hybrid_over_interference_only']:.0%})"
    )
    if figures["sensitivity"]:
        sensitivity = Table(title="the film's thickness and cut-on")
        for column in ("film", "thickness mm", "cut-on nm", "gain", "signal kept"):
            sensitivity.add_column(column, justify="right")
        for row in figures["sensitivity"]:
            sensitivity.add_row(
                row["case"],
                f"{row['thickness_mm']:g}",
                f"{row['cut_on_nm']:g}",
                f"{row['sbr_gain']:.3g}",
                f"{row['signal_kept']:.2f}",
            )
        _out.print(sensitivity)
    _out.print(f"plots: {', '.join(str(out_dir / name) for name in figures['figures'])}")


@spectra_app.command("fit-filter")
@user_errors
def fit_filter(
    curves: Annotated[
        Path,
        typer.Argument(help="CSV with wavelength_nm, aoi_deg and T (or Ts, Tp): a vendor's curves at several angles."),
    ],
    predict_aoi: Annotated[
        float | None,
        typer.Option(
            "--predict-aoi", help="Also predict the 50 % band edges of unpolarised light at this angle (degrees)."
        ),
    ] = None,
    fit_aoi: Annotated[
        str | None,
        typer.Option(
            "--fit-aoi", help="Comma-separated angles to fit on (degrees); default 0,20 if present, else all."
        ),
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Fit the angle-shifted band-pass model λ(θ) = λ₀√(1 − (sin θ/n_eff)²) to a vendor's curves.

    Tries one effective index, then one per edge, then one per edge and polarisation; for each,
    reports the fitted parameters, the residual, and the error of its 50 % band edges (nm) at the
    angles it was not fitted on. With --predict-aoi, prints edges_nm = [short, long] of the selected model.
    """
    from cm2optics.spectra.fit import fit_filter_models, read_filter_table

    if predict_aoi is not None and not (math.isfinite(predict_aoi) and 0 <= predict_aoi < 90):
        raise UserError(f"--predict-aoi = {predict_aoi}: must lie within 0–90°")
    angles = parse_float_list(fit_aoi, name="--fit-aoi", low=0, high=90, high_open=True, example="0,20")
    table = read_filter_table(curves)
    result = fit_filter_models(table, angles)
    data = result.to_dict(predict_aoi)
    if as_json:
        print(json.dumps(data, indent=2, ensure_ascii=False))
        return
    _out.print(f"{curves}: {data['table']}; fitted on {data['fit_aoi_deg']}°, held out {data['held_out_aoi_deg']}°")
    summary = Table(title="models, simplest first (errors: predicted − measured 50 % edges, nm)")
    for column in (
        "model",
        "n_eff short s/p",
        "n_eff long s/p",
        "rms residual",
        *(f"error at {a:g}°" for a in data["held_out_aoi_deg"]),
    ):
        summary.add_column(column, justify="right")
    for model in data["models"]:
        p = model["parameters"]
        errors = [
            ("" if h["scored"] else "(not scored) ")
            + ", ".join("—" if e is None else f"{e:+.2f}" for e in h["error_nm"])
            for h in model["held_out"]
        ]
        summary.add_row(
            model["model"],
            f"{p['n_eff_short_s']:.3f}/{p['n_eff_short_p']:.3f}",
            f"{p['n_eff_long_s']:.3f}/{p['n_eff_long_p']:.3f}",
            f"{model['rms_residual']:.4f}",
            *errors,
        )
    _out.print(summary)
    _out.print(f"selected: [bold]{data['selected_model']}[/] ({data['selection']})")
    if predict_aoi is not None:
        _out.print(f"50 % band edges at {predict_aoi:g}°: {data['edges_nm']} nm")
