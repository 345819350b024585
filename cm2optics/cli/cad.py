"""``cm2 cad``: printable parts, assembly, STL/STEP export."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from cm2optics.cli.options import JsonOption, OverwriteOption, PresetOption, output_folder, user_errors
from cm2optics.errors import UserError

__all__ = ["cad_app"]

out = Console()
err = Console(stderr=True, soft_wrap=True)
cad_app = typer.Typer(help="Parametric CAD: printable parts, assembly, STL/STEP export.", no_args_is_help=True)


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
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Export every part and the assembly, checked for printing.

    Writes one STL/STEP per part (each in its own frame) and `assembly.*` in the device
    frame (z = 0 on the sensor, +z towards the sample), PNG pictures, `design.yaml` and
    `manifest.json` with, per part: volume (mm³), bounding box (mm), watertight, minimum wall
    (mm); and for the assembly: interferences (empty when none) and the fit of every seated part.
    """
    from cm2optics.cad.export import FORMATS, export_design, size_text
    from cm2optics.cli.options import parse_names
    from cm2optics.design import load_preset

    chosen = parse_names(formats, name="--format", allowed=FORMATS, what="formats")
    if not 0.1 <= tolerance_um <= 100:
        raise UserError(f"--tolerance-um = {tolerance_um}: must lie within 0.1–100 µm")
    design = load_preset(preset)
    output_folder(out_dir, "cad export", inputs=[preset], overwrite=overwrite)
    manifest = export_design(
        design, out_dir, formats=chosen, tolerance_um=tolerance_um, pictures=pictures, show_progress=not as_json
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
