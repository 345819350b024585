"""``cm2 design``: inspect and validate system designs (YAML presets)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from cm2optics.cli.options import JsonOption, PresetOption, user_errors

__all__ = ["design_app"]

out = Console()
design_app = typer.Typer(help="Inspect and validate system designs (YAML presets).", no_args_is_help=True)


@design_app.command("show")
@user_errors
def design_show(
    preset: PresetOption = "cm2-v2",
    as_json: JsonOption = False,
    yaml_out: Annotated[bool, typer.Option("--yaml", help="Print the full design as YAML.")] = False,
) -> None:
    """Show a design's derived optics: focal length, magnification, object pixel, heights.

    The focal plane (object_plane_z_mm) is the plane of best focus (least RMS wavefront error);
    its paraxial conjugate lies focus_shift_mm farther out. Heights are in the device frame: z = 0 on the sensor surface, +z towards the sample.
    """
    from cm2optics.design import load_preset
    from cm2optics.optics.checks import require_plausible
    from cm2optics.reports.design import design_summary
    from cm2optics.spectra.library import egfp_emission_band_nm

    design = require_plausible(load_preset(preset), egfp_emission_band_nm())
    if yaml_out:
        sys.stdout.write(design.to_yaml())
        return
    summary = design_summary(design)
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    table = Table(
        title=f"{design.name}: optics at {design.imaging.design_wavelength_nm:g} nm "
        "(focal plane = best focus; paraxial values marked)"
    )
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for key, value in summary.items():
        table.add_row(key, str(value))
    out.print(table)


@design_app.command("validate")
@user_errors
def design_validate(path: Annotated[Path, typer.Argument(help="Design YAML to check.")]) -> None:
    """Check a design YAML: every field present, typed and in physical range."""
    from cm2optics.design import load_design
    from cm2optics.optics.checks import require_plausible
    from cm2optics.spectra.library import egfp_emission_band_nm

    design = require_plausible(load_design(path), egfp_emission_band_nm())
    out.print(f"[green]ok[/]: {path} is a valid design ({design.name}, hash {design.parameter_hash()})")


@design_app.command("presets")
def design_presets() -> None:
    """List the presets shipped with the package."""
    from cm2optics.design import available_presets

    for name in available_presets():
        print(name)
