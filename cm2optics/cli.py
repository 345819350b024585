"""The ``cm2`` command: one subcommand per pipeline stage.

A mistake a user can make (bad preset, bad option, missing file) ends in one line on stderr
and exit status 2; ``--json`` makes a command print machine-readable output on stdout.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

import cm2optics
from cm2optics.cli_options import JsonOption, PresetOption, user_errors
from cm2optics.design import SystemDesign, available_presets, load_preset
from cm2optics.emission.cli import psf_app
from cm2optics.illumination.cli import illum_app
from cm2optics.lsv.cli import lsv_app, simulate_command
from cm2optics.metrics.cli import evaluate_command
from cm2optics.optics import first_order
from cm2optics.optics.checks import require_plausible
from cm2optics.spectra.library import egfp_emission_band_nm
from cm2optics.recon.cli import reconstruct_command
from cm2optics.spectra.cli import spectra_app
from cm2optics.synth.cli import synth_command

app = typer.Typer(
    help="cm2optics: design, simulate and reconstruct computational miniature mesoscopes (CM²).\n\n"
    "Start with `cm2 design show --preset cm2-v2`, export printable parts with "
    "`cm2 cad export --preset cm2-v2 --out cad/`, or run everything at demo size with `cm2 demo`.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
design_app = typer.Typer(help="Inspect and validate system designs (YAML presets).", no_args_is_help=True)
cad_app = typer.Typer(help="Parametric CAD: printable parts, assembly, STL/STEP export.", no_args_is_help=True)
app.add_typer(design_app, name="design")
app.add_typer(cad_app, name="cad")
app.add_typer(spectra_app, name="spectra")
app.add_typer(illum_app, name="illum")
app.add_typer(psf_app, name="psf")
app.add_typer(lsv_app, name="lsv")
app.command("simulate")(simulate_command)
app.command("synth")(synth_command)
app.command("evaluate")(evaluate_command)
app.command("reconstruct")(reconstruct_command)

err = Console(stderr=True, soft_wrap=True)
out = Console()


def _version(value: bool) -> None:
    if value:
        print(f"cm2optics {cm2optics.__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show the version and exit.")
    ] = False,
) -> None:
    """cm2optics command line."""


# ----------------------------------------------------------------------------- design


def design_summary(design: SystemDesign) -> dict[str, float | str]:
    """Derived optics of a design (mm, µm as named): at the focal plane (best focus) and paraxial."""
    return {
        "name": design.name,
        "lenslet_focal_length_mm": round(first_order.lenslet_focal_length_mm(design), 4),
        "magnification": round(first_order.magnification(design), 4),
        "object_pixel_um": round(first_order.object_pixel_um(design), 4),
        "working_distance_mm": round(first_order.working_distance_mm(design), 4),
        "object_plane_z_mm": round(first_order.object_plane_z_mm(design), 4),
        "paraxial_magnification": round(first_order.paraxial_magnification(design), 4),
        "paraxial_object_plane_z_mm": round(first_order.paraxial_object_plane_z_mm(design), 4),
        "focus_shift_mm": round(first_order.focus_shift_mm(design), 4),
        "object_na": round(first_order.object_na(design), 4),
        "mla_flat_z_mm": design.imaging.mla_to_sensor_mm,
        "mla_vertex_z_mm": round(design.mla_vertex_z_mm, 4),
        "emission_filter_z_mm": round(design.emission_filter_z_mm, 4),
        "lens_corner_sag_mm": round(design.mla.corner_sag_mm, 5),
        "parameter_hash": design.parameter_hash(),
    }


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

    design = require_plausible(load_design(path), egfp_emission_band_nm())
    out.print(f"[green]ok[/]: {path} is a valid design ({design.name}, hash {design.parameter_hash()})")


@design_app.command("presets")
def design_presets() -> None:
    """List the presets shipped with the package."""
    for name in available_presets():
        print(name)


# ----------------------------------------------------------------------------- cad


@cad_app.command("export")
@user_errors
def cad_export(
    preset: PresetOption = "cm2-v2",
    out_dir: Annotated[
        Path, typer.Option("--out", "-o", help="Folder to write parts, pictures and manifest.json into.")
    ] = Path("out/cad"),
    formats: Annotated[str, typer.Option("--format", "-f", help="Comma-separated formats: stl, step.")] = "stl,step",
    tolerance_um: Annotated[
        float,
        typer.Option(
            "--tolerance-um",
            help="STL chord tolerance, µm (0.1–100); the default keeps lens faces ≈ 0.5 µm RMS from their spheres.",
        ),
    ] = 0.5,
    pictures: Annotated[
        bool, typer.Option("--pictures/--no-pictures", help="Render a PNG of each part and of the assembly.")
    ] = True,
    as_json: JsonOption = False,
) -> None:
    """Export every part and the assembly, checked for printing.

    Writes one STL/STEP per part (each in its own frame) and `assembly.*` in the device
    frame (z = 0 on the sensor, +z towards the sample), PNG pictures, `design.yaml` and
    `manifest.json` with, per part: volume (mm³), bounding box (mm), watertight, minimum wall
    (mm); and for the assembly: interferences (empty when none) and the fit of every seated part.
    """
    from cm2optics.cad.export import export_design, size_text

    design = load_preset(preset)
    manifest = export_design(
        design, out_dir, formats=formats, tolerance_um=tolerance_um, pictures=pictures, show_progress=not as_json
    )
    if as_json:
        print(json.dumps(manifest, indent=2, ensure_ascii=False))
        return
    table = Table(title=f"{design.name}: parts in {out_dir}")
    for column in ("part", "n", "volume mm³", "size mm", "watertight", "min wall mm", "printed"):
        table.add_column(column, no_wrap=True)
    for part in manifest["parts"]:
        table.add_row(
            part["name"],
            str(part["count"]),
            f"{part['volume_mm3']:.3f}",
            size_text(part["bbox_mm"]),
            "yes" if part["watertight"] else "[red]NO[/]",
            f"{part['min_wall_mm']:.3f}",
            "yes" if part["printed"] else "",
        )
    out.print(table)
    clashes = manifest["assembly"]["interferences"]
    out.print(f"interferences: {'none' if not clashes else clashes}")
    failed = [name for name, ok in manifest["checks"].items() if not ok]
    if failed:
        err.print(f"[bold red]checks failed:[/] {', '.join(failed)}")
        raise typer.Exit(1)


# ----------------------------------------------------------------------------- demo


@app.command("demo")
@user_errors
def demo(
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Folder for the report and its figures.")] = Path(
        "out/demo"
    ),
    preset: PresetOption = "cm2-v2",
) -> None:
    """Run every stage built so far at demo size and write `report.html` and `report.md`."""
    from cm2optics.demo import run_demo

    report = run_demo(load_preset(preset), out_dir)
    out.print(f"[green]demo report:[/] {report}")


if __name__ == "__main__":  # pragma: no cover
    app()
