"""``cm2 lsv build``, ``cm2 lsv validate`` and ``cm2 simulate``.

Register with ``app.add_typer(lsv_app, name="lsv")`` and ``app.command("simulate")(simulate_command)``.
The work is :func:`cm2optics.lsv.build.build_model`, :func:`cm2optics.lsv.validate.validate_model` and
:func:`cm2optics.lsv.simulate.simulate_measurement`; these only check options and format results.
"""

from __future__ import annotations

import functools
import json
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from cm2optics.cli.options import (
    JsonOption,
    OverwriteOption,
    PresetOption,
    check_output,
    parse_float_list,
    parse_int_list,
    user_errors,
)
from cm2optics.errors import UserError

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


#: Largest default grid a model may carry (voxels; 2³¹ float32 voxels are 8 GiB per volume copy).
MAX_GRID_VOXELS = 2**31


def _check_sizes(scan_dir: Path, patch_px: int | None, lateral_um: float | None, axial_um: float) -> None:
    """Refuse crops larger than the images and grids beyond :data:`MAX_GRID_VOXELS`, before any allocation."""
    import math

    from cm2optics.formats.scan import open_scan

    if axial_um <= 0 or not math.isfinite(axial_um):
        raise UserError(f"--axial-um = {axial_um}: must be a number > 0")
    if lateral_um is not None and (lateral_um <= 0 or not math.isfinite(lateral_um)):
        raise UserError(f"--lateral-um = {lateral_um}: must be a number > 0")
    index = open_scan(scan_dir)
    side = min(index.image(0).shape[-2:])
    if patch_px is not None and not 4 <= patch_px <= side:
        raise UserError(f"--patch-px = {patch_px}: must lie within 4–{side} px (the scan's images are {side} px)")
    if lateral_um is None:
        return
    xs, ys, zs = index.grid_axes_mm()
    shape = [
        int(math.floor(float(a[-1] - a[0]) * 1000.0 / step + 1e-9)) + 1
        for a, step in ((zs, axial_um), (ys, lateral_um), (xs, lateral_um))
    ]
    if math.prod(shape) > MAX_GRID_VOXELS:
        raise UserError(
            f"--lateral-um = {lateral_um:g}, --axial-um = {axial_um:g}: the default grid would be "
            f"{' × '.join(map(str, shape))} voxels (> {MAX_GRID_VOXELS:.3g}); choose coarser voxels"
        )


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
    axial_um: Annotated[
        float | None,
        typer.Option("--axial-um", help="Default grid's axial voxel, µm (default: the design's volume.axial_step_um)."),
    ] = None,
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
    focal_surface: Annotated[
        bool,
        typer.Option(
            "--focal-surface/--fixed-depth",
            help="Interpolate between lateral nodes at equal defocus from each lenslet's best-focus surface (field "
            "curvature, estimated from the scan) or at fixed depth.",
        ),
    ] = True,
    refine: Annotated[
        int,
        typer.Option(
            "--refine",
            help="With --focal-surface: lateral steps of the calibration grid cut this many times, where each "
            "lenslet's coefficients are precomputed along its surface (1–64).",
        ),
    ] = 2,
    rotate: Annotated[
        str,
        typer.Option(
            "--rotate",
            help="auto: turn each lateral neighbour's PSF to the source's azimuth about the lenslet's axis before "
            "the blend if nodes of the scan left out are predicted ≥ 10 % better so (the aberrations of a "
            "symmetric lens turn with the field); on; off (blend at a fixed orientation). Needs --refine ≥ 2.",
        ),
    ] = "auto",
    warp: Annotated[
        str,
        typer.Option(
            "--warp",
            help="auto: blend neighbouring PSFs by displacement interpolation (each warped about its focus to the "
            "interpolated focus size and elongation first) if nodes of the scan left out are predicted ≥ 10 % "
            "better so; on; off (linear blend). Needs --refine ≥ 2.",
        ),
    ] = "auto",
    memory_gb: Annotated[
        float,
        typer.Option(
            "--memory-gb",
            help="Crops larger than this (GiB) are kept in a temporary file and read a quarter of it at a time, "
            "with a randomized SVD streamed over them (a dense full-field scan); smaller ones are held in memory "
            "and decomposed exactly.",
        ),
    ] = 4.0,
    aberration_model: Annotated[
        int,
        typer.Option(
            "--aberration-model",
            help="N > 0: node PSFs from the nodal-aberration model (the preset's pupils traced at every node, its "
            "wavefront and vignetting fitted to them, each PSF's offset and flux fitted to the scan's crops) and the "
            "basis from its PSFs at N seeded random positions between the nodes (the rank is at most N); needs "
            "--oversample even ≥ 2 and the scan's fine ePSFs (epsf.h5) or whole-pixel frames at several sub-pixel "
            "phases (the offsets fitted to each frame at its own phase). 0: node PSFs and basis from the scan's crops.",
        ),
    ] = 0,
    node_coefficients: Annotated[
        str,
        typer.Option(
            "--node-coefficients",
            help="With --aberration-model: 'model' (node coefficients from its PSFs at the nodes) or 'scan' (from "
            "the scan's own fine ePSF crops projected on its basis: the basis alone from the model; needs epsf.h5).",
        ),
    ] = "model",
    per_lenslet_basis: Annotated[
        bool,
        typer.Option(
            "--per-lenslet-basis",
            help="Each lenslet its own basis of K single-lenslet PSFs (K = --rank; J·K terms in all) instead of one "
            "basis of K focus arrays: the same forward cost (each lenslet uses its own K), far more rank where the "
            "PSFs change over the field. Needs fine crops (a synthetic ePSF scan) or --oversample 1.",
        ),
    ] = False,
    preset: PresetOption = "cm2-v2",
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Build a 3D-LSV model from a PSF scan (measured or synthetic).

    Removes dark level, background and exposure; fits the imaging geometry (foci, magnification
    against depth, the axial shear from the on-axis stack); crops the foci around their chief rays
    with the shear undone; truncated SVD into K basis PSFs and coefficients on the calibration grid;
    each lenslet's best-focus surface, along which the coefficients are interpolated between
    lateral nodes (--fixed-depth: at fixed depth, as models without a surface), each lateral
    neighbour's PSF turned to the source's azimuth where the scan says so (--rotate), and
    neighbouring PSFs warped to the interpolated focus shape before the blend where it says so (--warp).
    Writes one HDF5 model with its provenance, and a report with the error against K, the first
    basis PSFs and coefficient maps. JSON keys include rank, nmse_calibration, nmse_vs_rank.
    """
    from cm2optics.design import load_preset
    from cm2optics.lsv.build import build_model

    if rank < 1:
        raise UserError(f"--rank = {rank}: must be ≥ 1")
    if trim < 0 or trim >= 1:
        raise UserError(f"--trim = {trim}: must lie within 0 ≤ trim < 1")
    if not 1 <= refine <= 64:
        raise UserError(f"--refine = {refine}: must lie within 1–64")
    if not memory_gb > 0:
        raise UserError(f"--memory-gb = {memory_gb}: must be > 0")
    if aberration_model < 0:
        raise UserError(f"--aberration-model = {aberration_model}: must be ≥ 0")
    if aberration_model and (oversample < 2 or oversample % 2):
        raise UserError(
            f"--aberration-model needs an ePSF basis (--oversample even ≥ 2), not --oversample {oversample}"
        )
    if node_coefficients not in ("model", "scan"):
        raise UserError(f"--node-coefficients = {node_coefficients!r}: must be model or scan")
    if node_coefficients == "scan" and not aberration_model:
        raise UserError("--node-coefficients scan needs --aberration-model N (the basis from its PSFs)")
    turn = {"auto": None, "on": True, "off": False}.get(rotate, "bad")
    if turn == "bad":
        raise UserError(f"--rotate = {rotate!r}: must be auto, on or off")
    if turn is True and refine < 2:
        raise UserError("--rotate on needs --refine ≥ 2 (the turned PSFs are blended on the refined grid)")
    warping = {"auto": None, "on": True, "off": False}.get(warp, "bad")
    if warping == "bad":
        raise UserError(f"--warp = {warp!r}: must be auto, on or off")
    if warping is True and refine < 2:
        raise UserError("--warp on needs --refine ≥ 2 (the warped PSFs are blended on the refined grid)")
    design = load_preset(preset)
    _check_sizes(scan_dir, patch_px, lateral_um, axial_um or design.volume.axial_step_um)
    model_path, folder = _build_paths(scan_dir, out, report_dir, no_report, preset, overwrite)
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
            focal_surface=focal_surface,
            refine=refine,
            rotate=turn,
            warp=warping,
            memory_bytes=int(memory_gb * 1024**3),
            node_psfs=_aberration_model(design, aberration_model),
            per_lenslet_basis=per_lenslet_basis,
            scan_node_coefficients=node_coefficients == "scan",
        )
    summary = _save_build(result, model_path, None if no_report else folder, oversample)
    if as_json:
        print(json.dumps(summary, indent=2, ensure_ascii=False))
        return
    _out.print(_build_table(model_path, summary))
    if "report" in summary:
        _out.print(f"report: {summary['report']}")


def _aberration_model(design: Any, dense: int) -> Any:
    """``build_model``'s node-PSF model for --aberration-model N (None for 0): the design's nodal-aberration model."""
    if not dense:
        return None
    from cm2optics.calibrate.aberration_build import aberration_psfs

    return functools.partial(aberration_psfs, design, dense=dense)


def _refit_node_model(model: Any, preset: str | None) -> Any:
    """validate --refit's node model: the build's aberration model (its design, random positions and
    seed) for a model built with --aberration-model, else None."""
    record = model.provenance.get("node_psfs")
    if record is None:
        return None
    from cm2optics.calibrate.aberration_build import aberration_psfs
    from cm2optics.design import load_preset

    name = preset or model.provenance.get("options", {}).get("design") or "cm2-v2"
    return functools.partial(
        aberration_psfs, load_preset(name), dense=int(record["dense_positions"]), seed=int(record.get("seed", 0))
    )


def _build_paths(
    scan_dir: Path, out: Path | None, report_dir: Path | None, no_report: bool, preset: str, overwrite: bool
) -> tuple[Path, Path]:
    """The model file (default SCAN_DIR.lsv.h5) and report folder (default MODEL_report/), both checked as outputs."""
    model_path = out or scan_dir.with_name(scan_dir.resolve().name + ".lsv.h5")
    check_output(model_path, command="lsv build", inputs=[scan_dir, preset], overwrite=overwrite)
    folder = report_dir or model_path.with_name(model_path.stem.replace(".lsv", "") + "_report")
    if not no_report:
        check_output(
            folder, command="lsv build", kind="folder", inputs=[scan_dir, preset, model_path], overwrite=overwrite
        )
    return model_path, folder


def _save_build(result: Any, model_path: Path, report_folder: Path | None, oversample: int) -> dict[str, Any]:
    """Save the model, write the report into ``report_folder`` (None: none); returns the summary for output."""
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.reports.lsv import write_build_report

    result.model.save(model_path)
    summary = {"model": str(model_path), **result.summary()}
    if oversample > 1:
        summary["epsf"] = result.model.provenance.get("epsf", {})
    summary["focal_surface"] = result.model.provenance.get("focal_surface")
    summary["rotation"] = result.model.provenance.get("rotation")
    if report_folder is not None:
        summary["report"] = str(write_build_report(result, report_folder))
        claim_folder(report_folder, "lsv build")
    return summary


def _build_table(model_path: Path, summary: dict[str, Any]) -> Table:
    """The built model's rank, calibration errors, positions, crop (px), default grid (µm) and
    whether its lateral neighbours are turned with the azimuth."""
    table = Table(title=f"LSV model {model_path}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    keys = ("rank", "nmse_calibration", "nmse_calibration_svd", "nmse_calibration_per_psf", "numerical_rank")
    for key in keys + ("n_positions", "patch_px"):
        value = summary[key]
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    grid = summary["default_grid"]
    table.add_row("default grid", f"{grid['shape']} × {[round(v, 3) for v in grid['voxel_um']]} µm")
    rotation = summary.get("rotation") or {}
    check = rotation.get("leave_one_out")
    turned = "yes" if rotation.get("turned") else "no"
    if check and check.get("nmse_turned") is not None:
        turned += (
            f" (nodes left out: NMSE {check['nmse_fixed_orientation']:.3g} fixed, {check['nmse_turned']:.3g} turned)"
        )
    table.add_row("neighbours turned with the azimuth", turned)
    warped = "yes" if rotation.get("warped") else "no"
    if check and check.get("nmse_warped") is not None:
        plain, with_warp = ("turned", "turned_warped") if rotation.get("turned") else ("fixed_orientation", "warped")
        warped += (
            f" (nodes left out: NMSE {check[f'nmse_{plain}']:.3g} linear, {check[f'nmse_{with_warp}']:.3g} warped)"
        )
    table.add_row("neighbours warped to the interpolated shape", warped)
    for key, value in _epsf_rows(summary.get("epsf") or {}):
        table.add_row(key, value)
    return table


def _epsf_rows(epsf: dict[str, Any]) -> list[tuple[str, str]]:
    """The build table's rows on the ePSF basis: its source, the phase coverage and the dithers pooled."""
    if not epsf:
        return []
    rows = [("ePSF oversample", f"{epsf['oversample']} ({epsf.get('source') or epsf.get('fallback', 'whole pixels')})")]
    coverage = epsf.get("phase_coverage")
    if coverage:
        rows.append(("sub-pixel phase bins visited (worst lenslet)", f"{coverage['min_bins_visited']:.0%}"))
    estimate = epsf.get("estimate") or {}
    if "nodes_per_neighbourhood" in estimate:
        pooled, phases = estimate["nodes_per_neighbourhood"], estimate["phase_bins_per_neighbourhood"]
        rows.append(
            (
                "frames pooled per node (dithers)",
                f"median {pooled['median']:g}, min {pooled['min']}; phase bins ≥ {phases['min']} of {phases['of']}; "
                f"{estimate['nodes_of_one_phase']} nodes of one phase",
            )
        )
    return rows


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
    refit: Annotated[
        bool,
        typer.Option(
            "--refit",
            help="Also leave-one-out in pixels with the model's build redone without the --heldout nodes: the node "
            "model (--aberration-model) refitted and the basis (per lenslet for a per-lenslet model) decomposed "
            "without them, each node predicted at its exact sub-pixel focus in its own frame (JSON key leave_out).",
        ),
    ] = False,
    preset: Annotated[
        str | None,
        typer.Option("--preset", help="Design whose pupils --refit traces (default: the model's own, from its build)."),
    ] = None,
    memory_gb: Annotated[
        float, typer.Option("--memory-gb", help="--refit: crops larger than this stay on disk.")
    ] = 4.0,
    as_json: JsonOption = False,
) -> None:
    """Error of a model at scan positions it was not built from.

    On its own calibration scan: leave-one-out (each held-out node predicted from its neighbours
    with the SVD redone without it). On another scan: the model's image of each position against
    the measured one. Both: against K, and for models built on a 2× sparser grid laterally or
    axially. With --refit (the calibration scan only): the issue's leave-one-out in pixels of the
    model as built, the node model and basis fitted again without the held-out nodes. JSON keys
    include nmse_heldout, nmse_heldout_vs_rank, nmse_subsampled; with --refit leave_out (nmse,
    nmse_median, nmse_full, nmse_per_lenslet, nmse_vs_terms).
    """
    from cm2optics.lsv.model import load_model
    from cm2optics.lsv.validate import validate_model

    if heldout < 1 or max_positions < 1:
        raise UserError("--heldout and --max-positions must be ≥ 1")
    if not memory_gb > 0:
        raise UserError(f"--memory-gb = {memory_gb}: must be > 0")
    wanted = parse_int_list(ranks or None, name="--ranks", low=1, example="8,16,32,64")
    model = load_model(model_path)
    node_psfs = _refit_node_model(model, preset) if refit else None
    with _progress(not as_json) as progress:
        result = validate_model(
            model,
            scan_dir,
            ranks=wanted,
            n_heldout=heldout,
            max_positions=max_positions,
            subsample=not no_subsample,
            seed=seed,
            progress=progress,
        )
        if refit:
            from cm2optics.lsv.leave_out import leave_out_nodes

            if result["method"] != "leave-one-out":
                raise UserError(f"--refit needs the model's own calibration scan; {scan_dir} is another scan")
            result["leave_out"] = leave_out_nodes(
                model,
                scan_dir,
                n_heldout=heldout,
                seed=seed,
                node_psfs=node_psfs,
                memory_bytes=int(memory_gb * 1024**3),
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
    leave_out = result.get("leave_out")
    if leave_out:
        _out.print(
            f"leave-one-out in pixels, refitted ({leave_out['basis']}, {leave_out['n_heldout']} nodes): NMSE mean "
            f"{leave_out['nmse']:.4g} (median {leave_out['nmse_median']:.4g}), full rank {leave_out['nmse_full']:.4g}"
        )
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
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Simulate a CM² measurement of a volume or of emitters through an LSV model.

    The image is scaled so that its brightest pixel is full scale (normalised intensity 1, as in
    the paper); with --noise, Poisson noise at --peak-photons and Gaussian read noise plus a dark
    offset are added (the paper's mixed noise model). Writes 16-bit counts and MEAS.yaml with the
    model, the scale (counts per model unit) and the noise settings. A .npy volume without
    --voxel-um is taken to be on the model's default grid spacing.
    """
    from cm2optics.lsv.simulate import simulate_measurement

    inputs = [model_path, volume_path, emitters_path]
    for path in (out, out.with_suffix(".yaml")):
        check_output(path, command="simulate", inputs=inputs, overwrite=overwrite)
    with _progress(not as_json) as progress:
        summary = simulate_measurement(
            out,
            model_path,
            volume_path=volume_path,
            emitters_path=emitters_path,
            voxel_um=parse_float_list(voxel_um, 3, name="--voxel-um", low=0, low_open=True, example="10,4.15,4.15"),
            noise=noise,
            peak_photons=peak_photons,
            read_noise=read_noise,
            offset=offset,
            bit_depth=bit_depth,
            per_lenslet=per_lenslet,
            lsi=lsi,
            seed=seed,
            subpixel_steps=subpixel_steps,
            progress=progress,
        )
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    _out.print(
        f"[green]measurement:[/] {out} {tuple(summary['shape'])} (max {summary['max_count']} counts; "
        f"sidecar {summary['sidecar']})"
    )
