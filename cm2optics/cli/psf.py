"""``cm2 psf``: synthetic PSF calibration scans and brute-force measurements of emitters.

Registered by :mod:`cm2optics.cli` as ``app.add_typer(psf_app, name="psf")``. User errors end in
one line and exit status 2 (:func:`cm2optics.cli.options.user_errors`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table

from cm2optics.cli.options import (
    BinningOption,
    JsonOption,
    OverwriteOption,
    PresetOption,
    check_dask_address,
    check_output,
    parse_int_list,
    user_errors,
)
from cm2optics.errors import UserError

__all__ = ["psf_app"]

out = Console()
err = Console(stderr=True)

psf_app = typer.Typer(
    help="Emission path and PSFs: point sources traced through filter, lenslets and film to the sensor "
    "(Mitsuba 3 / Dr.Jit ray trace + Fourier optics), written as PSF calibration scans or measurements.",
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)


@psf_app.command("simulate")
@user_errors
def simulate(
    preset: PresetOption = "cm2-v2",
    grid: Annotated[
        str | None,
        typer.Option(
            "--grid",
            help="NXxNYxNZ positions over the design's calibration volume (the square around the imaged field, "
            "1.25 × its depth, centred on the plane of best focus: 9x9x11 gives the paper's −4…4 mm in 1-mm and "
            "−0.5…0.5 mm in 100-µm steps). Default when --positions is not given: 9x9x11.",
        ),
    ] = None,
    positions: Annotated[
        Path | None,
        typer.Option(
            "--positions", help="CSV with columns x_mm,y_mm,z_mm (object space; a full grid) instead of --grid."
        ),
    ] = None,
    binning: BinningOption = 1,
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Scan folder to write.")] = Path("out/psf-scan"),
    dask_address: Annotated[
        str | None,
        typer.Option("--dask-address", help="Dask scheduler to run on (tcp://host:8786); default: a local cluster."),
    ] = None,
    workers: Annotated[
        int | None, typer.Option("--workers", help="Local worker processes (default: one per core).")
    ] = None,
    field_mm: Annotated[
        float | None, typer.Option("--field-mm", help="Lateral extent of --grid, mm (default: volume.field_mm).")
    ] = None,
    depth_mm: Annotated[
        float | None, typer.Option("--depth-mm", help="Axial extent of --grid, mm (default: 1.25 × volume.depth_mm).")
    ] = None,
    pinhole_um: Annotated[float, typer.Option("--pinhole-um", help="Pinhole diameter, µm.")] = 5.0,
    profile: Annotated[
        str,
        typer.Option(
            "--profile",
            help="Angular emission of the source: gaussian (a pinhole behind a diffuser, the paper's calibration; "
            "--half-angle-deg), isotropic (a fluorescent bead) or lambertian.",
        ),
    ] = "gaussian",
    half_angle_deg: Annotated[
        float,
        typer.Option("--half-angle-deg", help="1/e² half-angle of the pinhole's Gaussian emission profile, degrees."),
    ] = 26.0,
    band_nm: Annotated[float, typer.Option("--band-nm", help="Widest wavelength band traced, nm.")] = 10.0,
    oversample: Annotated[
        int,
        typer.Option(
            "--oversample",
            help="S > 1: also write each position's effective PSF (the PSF integrated over one saved pixel) on a "
            "grid S times finer than the saved pixels, as epsf.h5 beside the frames (for cm2 lsv build --oversample).",
        ),
    ] = 1,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Simulate a PSF calibration scan: positions.csv, 16-bit TIFFs, scan.yaml (the measured-scan format),
    montage.png and manifest.json in --out.

    Positions are in object space: x_mm, y_mm from the central lenslet's axis, z_mm from the nominal
    focal plane (the plane of best focus), +z towards the device. Images: the sensor frame (column along +x, row along +y),
    binned; scan.yaml's pixel_um is the saved pitch. The positions run on Dask with a progress bar;
    an interrupted run resumes where it stopped when run again with the same options (its work
    folder .OUT.psf-work sits beside --out). --out must be new, empty or an earlier scan of this
    command; files of other programs in it are never deleted (--overwrite writes beside them).
    """
    from cm2optics.design import load_preset
    from cm2optics.emission.psf import PSFSettings
    from cm2optics.emission.scan import ScanSettings, calibration_grid_mm, read_positions_csv
    from cm2optics.emission.source import scan_source

    if grid is not None and positions is not None:
        raise UserError("give --grid or --positions, not both")
    counts = parse_int_list(grid or "9x9x11", 3, name="--grid", sep="x", low=1, high=101, example="9x9x11")
    design = load_preset(preset)
    check_output(out_dir, command="psf simulate", kind="folder", inputs=[positions, preset], overwrite=overwrite)
    check_dask_address(dask_address)
    if positions is not None:
        points = read_positions_csv(positions)
    else:
        points = calibration_grid_mm(design, counts, field_mm, depth_mm)
    settings = ScanSettings(
        psf=PSFSettings(binning=binning, band_nm=band_nm, oversample=oversample),
        source=scan_source(profile, pinhole_um, half_angle_deg),
    )
    manifest = _run_scan(design, points, out_dir, settings, dask_address, workers, progress=not as_json)
    if as_json:
        print(json.dumps({"out": str(out_dir), **manifest}, indent=2, ensure_ascii=False))
        return
    out.print(_scan_table(design, manifest, binning, out_dir))


def _run_scan(
    design: Any,
    points: Any,
    out_dir: Path,
    settings: Any,
    dask_address: str | None,
    workers: int | None,
    *,
    progress: bool,
) -> dict[str, Any]:
    """simulate_scan under the output folder's lock; its manifest with the total wall time (s).
    An interruption keeps the finished positions and exits with 130."""
    from cm2optics.emission.scan import simulate_scan
    from cm2optics.formats.outputs import output_lock

    start = time.perf_counter()
    try:
        with output_lock(out_dir, "psf simulate"):
            manifest = simulate_scan(
                design, points, out_dir, settings, dask_address=dask_address, workers=workers, progress=progress
            )
    except KeyboardInterrupt:
        err.print(
            f"[yellow]interrupted: finished positions are kept; run the same command again to resume into {out_dir}[/]"
        )
        raise typer.Exit(130) from None
    manifest["timings"]["total_s"] = round(time.perf_counter() - start, 2)
    return manifest


def _scan_table(design: Any, manifest: dict[str, Any], binning: int, out_dir: Path) -> Table:
    """The scan's summary: positions, grid, pixel (µm), wall and per-position time (s), exposure (ms)."""
    table = Table(title=f"{design.name}: PSF scan in {out_dir}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    rows = [
        ("positions", manifest["inputs"]["positions"]),
        ("grid (x × y × z)", " × ".join(str(n) for n in manifest["inputs"]["grid_shape"])),
        ("binning / pixel", f"{binning} / {design.sensor.pixel_um * binning:g} µm"),
        ("wall time", f"{manifest['timings']['total_s']:.1f} s"),
        ("per position (worker)", f"{manifest['timings']['per_position_s_mean']:.3f} s mean"),
        ("exposure", f"{manifest['metrics']['exposure_ms_min']:.3g}–{manifest['metrics']['exposure_ms_max']:.3g} ms"),
    ]
    for key, value in rows:
        table.add_row(key, str(value))
    return table


@psf_app.command("image")
@user_errors
def image(
    emitters: Annotated[
        Path, typer.Option("--emitters", "-e", help="CSV x_um,y_um,z_um,diameter_um,intensity (object space).")
    ],
    preset: PresetOption = "cm2-v2",
    binning: BinningOption = 1,
    out_path: Annotated[
        Path, typer.Option("--out", "-o", help="Measurement TIFF to write (a .yaml sidecar goes beside it).")
    ] = Path("out/psf-image/measurement.tif"),
    fill: Annotated[float, typer.Option("--fill", help="Brightest pixel as a fraction of full scale.")] = 0.8,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Render a measurement of a few emitters by tracing each one through the emission path: the
    brute-force reference that the 3D-LSV model is checked against.

    Emitters: x_um, y_um from the central lenslet's axis, z_um from the nominal focal plane (+z towards
    the device), bead diameter in µm, relative intensity. Writes a 16-bit TIFF (sensor frame, column
    along +x, row along +y) and a YAML sidecar with the count scale.
    """
    from cm2optics.design import load_preset
    from cm2optics.emission.image import render_emitters, write_traced_measurement
    from cm2optics.emission.psf import PSFSettings
    from cm2optics.formats.emitters import read_emitters

    design = load_preset(preset)
    for path in (out_path, out_path.with_suffix(".yaml")):
        check_output(path, command="psf image", inputs=[emitters, preset], overwrite=overwrite)
    table = read_emitters(emitters)
    settings = PSFSettings(binning=binning)
    start = time.perf_counter()
    frame = render_emitters(design, table, settings, progress=not as_json)
    elapsed = time.perf_counter() - start
    tif, sidecar = write_traced_measurement(
        out_path, frame, design, binning, fill=fill, extra={"emitters": str(emitters), "count": len(table)}
    )
    result = {
        "out": str(tif),
        "sidecar": str(sidecar),
        "emitters": len(table),
        "shape": list(frame.shape),
        "pixel_um": design.sensor.pixel_um * binning,
        "seconds": round(elapsed, 2),
    }
    if as_json:
        print(json.dumps(result, indent=2))
        return
    out.print(
        f"[green]measurement:[/] {tif} ({len(table)} emitters, {frame.shape[1]}×{frame.shape[0]} px, {elapsed:.1f} s)"
    )
