"""``cm2 lsv build``, ``cm2 lsv validate`` and ``cm2 simulate``.

Register with ``app.add_typer(lsv_app, name="lsv")`` and ``app.command("simulate")(simulate_command)``.
User errors end in one line and exit status 2 (:func:`cm2optics.cli_options.user_errors`).
"""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cm2optics.cli_options import JsonOption, PresetOption, user_errors

__all__ = ["lsv_app", "simulate_command"]

lsv_app = typer.Typer(
    help="The 3D linear-shift-variant (LSV) forward model: build it from a PSF scan, validate it on held-out positions.",
    no_args_is_help=True,
)

_out = Console()
_err = Console(stderr=True)


@contextmanager
def _progress(enabled: bool):
    """A rich progress bar on stderr fed by ``callback(stage, done, total)``."""
    if not enabled:
        yield None
        return
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=_err,
        transient=True,
    ) as bar:
        tasks: dict[str, Any] = {}

        def callback(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        yield callback


def _parse_ranks(text: str | None) -> tuple[int, ...] | None:
    if not text:
        return None
    try:
        ranks = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--ranks = {text!r}: must be comma-separated integers, e.g. 8,16,32,64") from None
    if any(k < 1 for k in ranks):
        raise ValueError(f"--ranks = {text!r}: every rank must be ≥ 1")
    return ranks


@lsv_app.command("build")
@user_errors
def build(
    scan_dir: Annotated[Path, typer.Argument(help="PSF scan folder (positions.csv, TIFFs, scan.yaml).")],
    rank: Annotated[int, typer.Option("--rank", "-k", help="K, the number of basis PSFs.")] = 64,
    out: Annotated[
        Path | None, typer.Option("--out", "-o", help="Model file to write (HDF5); default SCAN_DIR.lsv.h5.")
    ] = None,
    report_dir: Annotated[
        Path | None, typer.Option("--report", help="Folder for figures and report; default MODEL_report/.")
    ] = None,
    no_report: Annotated[bool, typer.Option("--no-report", help="Skip the figures and report.")] = False,
    patch_px: Annotated[
        int | None, typer.Option("--patch-px", help="Crop side per focus, px (default 160 at full resolution).")
    ] = None,
    lateral_um: Annotated[
        float | None, typer.Option("--lateral-um", help="Default grid's lateral voxel, µm (default: one sensor pixel).")
    ] = None,
    axial_um: Annotated[float, typer.Option("--axial-um", help="Default grid's axial voxel, µm.")] = 10.0,
    trim: Annotated[
        float,
        typer.Option("--trim", help="Energy share the crops' dark margins may hold when cut (0: keep the full crops)."),
    ] = 1e-6,
    oversample: Annotated[
        int,
        typer.Option(
            "--oversample",
            help="S > 1: effective-PSF basis on a grid S times finer than the pixels, sampled at each focus's exact "
            "sub-pixel position (from the scan's epsf.h5, else estimated from the whole-pixel frames); 1: whole pixels.",
        ),
    ] = 1,
    preset: PresetOption = "cm2-v2",
    as_json: JsonOption = False,
) -> None:
    """Build a 3D-LSV model from a PSF scan (measured or synthetic).

    Removes dark level, background and exposure; fits the imaging geometry (foci, magnification
    against depth, the axial shear from the on-axis stack); crops the foci around their chief rays
    with the shear undone; truncated SVD into K basis PSFs and coefficients on the calibration grid.
    Writes one HDF5 model with its provenance, and a report with the error against K, the first
    basis PSFs and coefficient maps. JSON keys include rank, nmse_calibration, nmse_vs_rank.
    """
    from cm2optics.design import load_preset
    from cm2optics.lsv.build import build_model
    from cm2optics.lsv.report import write_build_report

    if rank < 1:
        raise ValueError(f"--rank = {rank}: must be ≥ 1")
    if trim < 0 or trim >= 1:
        raise ValueError(f"--trim = {trim}: must lie within 0 ≤ trim < 1")
    design = load_preset(preset)
    model_path = out or scan_dir.with_name(scan_dir.name.rstrip("/") + ".lsv.h5")
    with _progress(not as_json) as progress:
        result = build_model(
            scan_dir,
            rank=rank,
            patch_px=patch_px,
            lateral_um=lateral_um,
            axial_um=axial_um,
            design=design,
            trim=trim or None,
            progress=progress,
            oversample=oversample,
        )
    result.model.save(model_path)
    summary = {"model": str(model_path), **result.summary()}
    if oversample > 1:
        summary["epsf"] = result.model.provenance.get("epsf", {})
    if not no_report:
        folder = report_dir or model_path.with_name(model_path.stem.replace(".lsv", "") + "_report")
        summary["report"] = str(write_build_report(result, folder))
    if as_json:
        print(json.dumps(summary, indent=2, ensure_ascii=False))
        return
    table = Table(title=f"LSV model {model_path}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for key in ("rank", "nmse_calibration", "nmse_calibration_per_psf", "numerical_rank", "n_positions", "patch_px"):
        value = summary[key]
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    grid = summary["default_grid"]
    table.add_row("default grid", f"{grid['shape']} × {[round(v, 3) for v in grid['voxel_um']]} µm")
    _out.print(table)
    if "report" in summary:
        _out.print(f"report: {summary['report']}")


@lsv_app.command("validate")
@user_errors
def validate(
    model_path: Annotated[Path, typer.Argument(metavar="MODEL", help="Model file from `cm2 lsv build`.")],
    scan_dir: Annotated[
        Path, typer.Argument(help="The calibration scan (leave-one-out) or a second scan (held-out positions).")
    ],
    ranks: Annotated[str | None, typer.Option("--ranks", help="Ranks to report, e.g. 8,16,32,64.")] = None,
    heldout: Annotated[int, typer.Option("--heldout", help="Held-out nodes for leave-one-out.")] = 48,
    max_positions: Annotated[
        int, typer.Option("--max-positions", help="Positions of a second scan to compare at most.")
    ] = 200,
    no_subsample: Annotated[
        bool, typer.Option("--no-subsample", help="Skip the sparser-grid (2× lateral / 2× axial) models.")
    ] = False,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the held-out sample.")] = 0,
    as_json: JsonOption = False,
) -> None:
    """Error of a model at scan positions it was not built from.

    On its own calibration scan: leave-one-out (each held-out node predicted from its neighbours
    with the SVD redone without it). On another scan: the model's image of each position against
    the measured one. Both: against K, and for models built on a 2× sparser grid laterally or
    axially. JSON keys include nmse_heldout, nmse_heldout_vs_rank, nmse_subsampled.
    """
    from cm2optics.lsv.model import load_model
    from cm2optics.lsv.validate import validate_model

    if heldout < 1 or max_positions < 1:
        raise ValueError("--heldout and --max-positions must be ≥ 1")
    model = load_model(model_path)
    with _progress(not as_json) as progress:
        result = validate_model(
            model,
            scan_dir,
            ranks=_parse_ranks(ranks),
            n_heldout=heldout,
            max_positions=max_positions,
            subsample=not no_subsample,
            seed=seed,
            progress=progress,
        )
    if as_json:
        print(json.dumps(result, indent=2, ensure_ascii=False))
        return
    table = Table(title=f"{model_path} on {scan_dir} ({result['method']}, {result['n_heldout']} positions)")
    table.add_column("K", justify="right")
    table.add_column("held-out NMSE", justify="right")
    for k, v in result["nmse_heldout_vs_rank"].items():
        table.add_row(k, "—" if v is None else f"{v:.4g}")
    _out.print(table)
    if "nmse_subsampled" in result:
        sub = result["nmse_subsampled"]
        _out.print(
            f"sparser grid (K = {min(model.rank, max(int(k) for k in result['nmse_heldout_vs_rank']))}): "
            f"lateral 2× → {sub['lateral_2x']:.4g}, axial 2× → {sub['axial_2x']:.4g}"
        )


@user_errors
def simulate_command(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Measurement TIFF to write (16-bit counts, YAML sidecar beside it).")
    ],
    model_path: Annotated[Path, typer.Option("--model", "-m", help="LSV model file from `cm2 lsv build`.")],
    volume_path: Annotated[
        Path | None, typer.Option("--volume", help="Volume (z, y, x): TIFF with ImageJ spacing or .npy.")
    ] = None,
    emitters_path: Annotated[
        Path | None, typer.Option("--emitters", help="Emitter CSV: x_um,y_um,z_um,diameter_um,intensity.")
    ] = None,
    voxel_um: Annotated[
        str | None, typer.Option("--voxel-um", help="Voxel pitch z,y,x in µm (for .npy, or to override).")
    ] = None,
    noise: Annotated[bool, typer.Option("--noise", help="Add Poisson photon noise and Gaussian read noise.")] = False,
    peak_photons: Annotated[
        float, typer.Option("--peak-photons", help="Photons at the brightest pixel (Poisson noise).")
    ] = 500.0,
    read_noise: Annotated[
        float, typer.Option("--read-noise", help="Gaussian read noise, share of full scale.")
    ] = 0.017,
    offset: Annotated[float, typer.Option("--offset", help="Dark offset, share of full scale (with --noise).")] = 0.048,
    bit_depth: Annotated[int, typer.Option("--bit-depth", help="ADC bits of the written counts.")] = 12,
    per_lenslet: Annotated[
        bool, typer.Option("--per-lenslet", help="Write the J crosstalk-free images as pages instead.")
    ] = False,
    lsi: Annotated[
        bool, typer.Option("--lsi", help="Use the depth-wise LSI baseline of the V1 paper instead of the LSV model.")
    ] = False,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the noise.")] = 0,
    subpixel_steps: Annotated[
        int,
        typer.Option(
            "--subpixel-steps",
            help="Emitters: sub-pixel positions rounded to 1/N px so that emitters share shifted PSFs (fast for "
            "thousands); 0 places every emitter exactly.",
        ),
    ] = 4,
    as_json: JsonOption = False,
) -> None:
    """Simulate a CM² measurement of a volume or of emitters through an LSV model.

    The image is scaled so that its brightest pixel is full scale (normalised intensity 1, as in
    the paper); with --noise, Poisson noise at --peak-photons and Gaussian read noise plus a dark
    offset are added (the paper's mixed noise model). Writes 16-bit counts and MEAS.yaml with the
    model, the scale (counts per model unit) and the noise settings. A .npy volume without
    --voxel-um is taken to be on the model's default grid spacing.
    """
    import numpy as np
    import tifffile
    import yaml

    from cm2optics.io import write_atomic, write_text_atomic
    from cm2optics.lsv.model import load_model
    from cm2optics.volume_io import read_emitters, read_volume

    if (volume_path is None) == (emitters_path is None):
        raise ValueError("give exactly one of --volume and --emitters")
    if bit_depth not in (8, 10, 12, 14, 16):
        raise ValueError(f"--bit-depth = {bit_depth}: must be one of 8, 10, 12, 14, 16")
    if not (peak_photons > 0 and read_noise >= 0 and 0 <= offset < 1):
        raise ValueError("--peak-photons must be > 0, --read-noise ≥ 0, --offset within [0, 1)")
    if out.suffix.lower() not in (".tif", ".tiff"):
        raise ValueError(f"--out {out}: the measurement is written as a TIFF (.tif)")
    if not 0 <= subpixel_steps <= 64:
        raise ValueError(f"--subpixel-steps = {subpixel_steps}: must lie within 0–64 (0: exact placement)")
    model = load_model(model_path)
    if lsi:
        from cm2optics.lsv.lsi import lsi_model

        model = lsi_model(model)
    spacing = None
    if voxel_um:
        try:
            spacing = tuple(float(v) for v in voxel_um.split(","))
        except ValueError:
            raise ValueError(f"--voxel-um = {voxel_um!r}: must be three numbers z,y,x in µm") from None
        if len(spacing) != 3:
            raise ValueError(f"--voxel-um = {voxel_um!r}: must be three numbers z,y,x in µm")
    with _progress(not as_json) as progress:
        if volume_path is not None:
            from cm2optics.volume_io import VolumeGrid

            if spacing is None and volume_path.suffix.lower() == ".npy":
                spacing = model.default_grid.voxel_um
            volume, grid = read_volume(volume_path, spacing)
            grid = VolumeGrid(volume.shape, grid.voxel_um)
            image = model.operator(grid).forward(volume, per_lenslet=per_lenslet, progress=progress)
            source = {"volume": str(volume_path), "grid": grid.to_dict()}
        else:
            emitters = read_emitters(emitters_path)
            image = model.forward_sparse(emitters, per_lenslet=per_lenslet, subpixel_steps=subpixel_steps or None)
            source = {
                "emitters": str(emitters_path),
                "count": len(emitters),
                "subpixel_steps": subpixel_steps or "exact",
            }
    image = np.asarray(image, dtype=np.float64)
    peak = float(image.max())
    if not peak > 0:
        raise ValueError("the simulated image is empty (nothing in the volume reaches the sensor)")
    normalised = np.clip(image / peak, 0, None)
    rng = np.random.default_rng(seed)
    if noise:
        normalised = rng.poisson(normalised * peak_photons) / peak_photons
        normalised = normalised + offset + rng.normal(0.0, read_noise, normalised.shape)
    full = 2**bit_depth - 1
    counts = np.clip(np.round(normalised * full), 0, full).astype(np.uint16)
    write_atomic(out, lambda tmp: tifffile.imwrite(tmp, counts, photometric="minisblack"))
    sidecar = {
        "model": str(model_path),
        "baseline": "lsi" if lsi else "lsv",
        "source": source,
        "per_lenslet": per_lenslet,
        "bit_depth": bit_depth,
        "counts_per_unit": float(full / peak),
        "noise": {"poisson_peak_photons": peak_photons, "read_noise": read_noise, "offset": offset, "seed": seed}
        if noise
        else None,
        "pixel_um": model.pixel_um,
    }
    sidecar_path = out.with_suffix(".yaml")
    write_text_atomic(sidecar_path, yaml.safe_dump(sidecar, sort_keys=False, allow_unicode=True))
    summary = {
        "measurement": str(out),
        "sidecar": str(sidecar_path),
        "shape": list(counts.shape),
        "max_count": int(counts.max()),
        "mean_count": float(counts.mean()),
        "counts_per_unit": sidecar["counts_per_unit"],
    }
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    _out.print(
        f"[green]measurement:[/] {out} {tuple(counts.shape)} (max {summary['max_count']} counts; sidecar {sidecar_path})"
    )
