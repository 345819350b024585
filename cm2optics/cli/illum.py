"""``cm2 illum``: trace the illumination path and search for better collimators.

Registered by :mod:`cm2optics.cli` as ``app.add_typer(illum_app, name="illum")``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table

from cm2optics.cli.options import (
    JsonOption,
    OverwriteOption,
    PresetOption,
    check_dask_address,
    check_output,
    output_folder,
    parse_float_list,
    user_errors,
)
from cm2optics.errors import UserError
from cm2optics.illumination.metrics import DEFINITIONS, IlluminationFigures

__all__ = ["illum_app"]

err = Console(stderr=True)
out = Console()

_DEFINITIONS_HELP = "\n\n".join(f"{name}: {text}." for name, text in DEFINITIONS.items())

illum_app = typer.Typer(
    help="Illumination: ray-trace LED → collimator → excitation filter → sample plane (Mitsuba 3 / Dr.Jit).\n\n"
    "Figures of merit (each with its Monte Carlo standard error):\n\n" + _DEFINITIONS_HELP,
    no_args_is_help=True,
    context_settings={"help_option_names": ["-h", "--help"]},
)


#: The inputs of ``optimize`` and ``robustness`` (``run`` words them at more length).
LedProfileOption = Annotated[
    Path | None, typer.Option("--led-profile", help="LED angular profile CSV; default Lambertian.")
]
LedSpectrumOption = Annotated[
    Path | None, typer.Option("--led-spectrum", help="LED spectrum CSV; default: the spectra library's model.")
]
FilterTableOption = Annotated[
    Path | None,
    typer.Option("--filter-table", help="Excitation filter angle table; default: the model of excitation_filter."),
]

#: The error ranges of ``robustness`` and of ``optimize --robust-samples``.
LedPlacementOption = Annotated[
    float, typer.Option("--led-placement-um", help="LED centre placement error, ± µm in each of x and y.")
]
UnitTiltOption = Annotated[
    float, typer.Option("--unit-tilt-deg", help="Unit tilt error about each of its x and y axes, ± degrees.")
]
SurfaceRmsOption = Annotated[
    float, typer.Option("--surface-rms-um", help="Printer surface error of the collimator, µm RMS.")
]


def _tolerances(led_placement_um: float, unit_tilt_deg: float, surface_rms_um: float) -> Any:
    """The :class:`~cm2optics.illumination.robustness.Tolerances` of the options (a UserError if out of range)."""
    from cm2optics.illumination.robustness import Tolerances

    try:
        return Tolerances(1e-3 * led_placement_um, unit_tilt_deg, surface_rms_um)
    except ValueError as error:
        raise UserError(f"tolerances: {error}") from None


def _format(estimate: Any, percent: bool = False, digits: int = 3) -> str:
    value, stderr = estimate.value, estimate.stderr
    if not math.isfinite(value):
        return "–"
    if percent:
        return f"{100 * value:.1f} ± {100 * stderr:.1f} %"
    return f"{value:.{digits}g} ± {stderr:.2g}"


def figures_table(results: list[IlluminationFigures], title: str) -> Table:
    """The comparison as a rich table: one column per design."""
    table = Table(title=title)
    table.add_column("figure")
    for result in results:
        table.add_column(result.label, justify="right")
    rows = [
        ("throughput", lambda f: _format(f.throughput, True)),
        ("delivered_fraction (Ø field)", lambda f: _format(f.delivered_fraction, True)),
        ("power_mw (array)", lambda f: _format(f.power_mw)),
        ("uniformity_cv", lambda f: _format(f.uniformity_cv, True) + f" (noise {100 * f.uniformity_cv_noise:.1f} %)"),
        ("uniformity_min_max", lambda f: _format(f.uniformity_min_max)),
        ("fraction_within_30deg", lambda f: _format(f.fraction_within_30deg, True)),
        (
            "beam half-angle 50 % / 90 % (deg)",
            lambda f: f"{f.beam_half_angle_50_deg.value:.1f} / {f.beam_half_angle_90_deg.value:.1f}",
        ),
        ("absorbed", lambda f: _format(f.ledger["absorbed"], True)),
        ("escaped", lambda f: _format(f.ledger["escaped"], True)),
        ("rays (all LEDs)", lambda f: f"{f.rays:,}"),
        ("trace time (s)", lambda f: f"{f.seconds:.2f}"),
    ]
    for name, cell in rows:
        table.add_row(name, *[cell(r) for r in results])
    return table


@illum_app.command("run")
@user_errors
def run(
    preset: PresetOption = "cm2-v2",
    collimator: Annotated[
        Path | None,
        typer.Option(
            "--collimator", help="A collimator STL (mm) to trace beside the V1 baseline and the design's own part."
        ),
    ] = None,
    led_position: Annotated[
        str | None,
        typer.Option(
            "--led-position", help="Centre of the LED's emitting surface in the STL's frame, X,Y,Z mm (default 0,0,0)."
        ),
    ] = None,
    led_axis: Annotated[
        str | None,
        typer.Option("--led-axis", help="Direction the LED emits in, in the STL's frame, X,Y,Z (default 0,0,1)."),
    ] = None,
    rays: Annotated[
        int, typer.Option("--rays", "-n", help="LED rays per design, split over the LEDs (≥ 1000).")
    ] = 1_000_000,
    led_profile: Annotated[
        Path | None,
        typer.Option(
            "--led-profile", help="LED angular profile CSV (angle_deg,relative_intensity); default Lambertian."
        ),
    ] = None,
    led_spectrum: Annotated[
        Path | None,
        typer.Option(
            "--led-spectrum",
            help="LED spectrum CSV (wavelength_nm,relative_power); default: spectra library model at led.peak_nm.",
        ),
    ] = None,
    filter_table: Annotated[
        Path | None,
        typer.Option(
            "--filter-table",
            help="Excitation filter angle table (wavelength_nm,aoi_deg,Ts,Tp or T), fitted with the spectra models; default: the model of excitation_filter.",
        ),
    ] = None,
    no_filter: Annotated[
        bool, typer.Option("--no-filter", help="Leave the excitation filter out (a bare optical trace).")
    ] = False,
    no_housing: Annotated[
        bool, typer.Option("--no-housing", help="Leave the absorbing housings and imaging tower out.")
    ] = False,
    flat_normals: Annotated[
        bool, typer.Option("--flat-normals", help="Trace collimators as their flat facets, not smooth surfaces.")
    ] = False,
    led_flux_mw: Annotated[
        float | None, typer.Option("--led-flux-mw", help="Radiant flux of each LED, mW (default: led.radiant_flux_mw).")
    ] = None,
    bin_mm: Annotated[
        float, typer.Option("--bin-mm", help="Side of the uniformity bins on the sample plane, mm.")
    ] = 0.5,
    seed: Annotated[int, typer.Option("--seed", help="Random seed: the same seed gives the same numbers.")] = 0,
    out_dir: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for the irradiance maps (PNG) and illumination.json.")
    ] = Path("out/illum"),
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Trace the V1 baseline (bare LED + filter), the design's collimator (CAD part) and
    optionally an STL, all in the same setup: four LEDs at their tilt and offset, filter,
    housings, sample plane at the nominal focal plane.

    --json prints, for the last design (the STL if given, else the design's collimator):
    throughput, delivered_fraction, power_mw, uniformity_cv, uniformity_min_max,
    fraction_within_30deg, beam_half_angle_50_deg, beam_half_angle_90_deg (each with
    *_stderr), uniformity_cv_noise, ledger, rays, per_led, `designs` with every design's
    figures, and spectral_ceiling (the most of the LED's power the run's filter passes at normal
    incidence, from --filter-table and --led-spectrum when given, the models otherwise). Definitions: see `cm2 illum --help`. The authors' part, for example:
    --collimator CM2_V2_freeform_illuminator.stl --led-position 0,0,1 --led-axis 0,0,-1.
    """
    from cm2optics.design import load_preset
    from cm2optics.illumination.run import run_illumination
    from cm2optics.optics.backend import variant

    design = load_preset(preset)
    inputs = [preset, collimator, led_profile, led_spectrum, filter_table]
    check_output(out_dir, command="illum run", kind="folder", inputs=inputs, overwrite=overwrite)
    vector = {"n": 3, "example": "0,0,1"}

    def progress(label: str) -> None:
        if not as_json:
            err.print(f"tracing [bold]{label}[/] ({rays:,} rays on {variant().variant})")

    document, results = run_illumination(
        design,
        out_dir,
        collimator=collimator,
        led_position=parse_float_list(led_position, name="--led-position", **vector),
        led_axis=parse_float_list(led_axis, name="--led-axis", **vector),
        rays=rays,
        led_profile=led_profile,
        led_spectrum=led_spectrum,
        filter_table=filter_table,
        no_filter=no_filter,
        no_housing=no_housing,
        flat_normals=flat_normals,
        led_flux_mw=led_flux_mw,
        bin_mm=bin_mm,
        seed=seed,
        progress=progress,
    )
    if as_json:
        print(json.dumps(document, indent=2, ensure_ascii=False))
        return
    out.print(figures_table(results, f"{design.name}: illumination, {rays:,} rays per design ({variant().variant})"))
    if document["spectral_ceiling"] is not None:
        out.print(
            f"spectral ceiling: the excitation filter passes at most {document['spectral_ceiling']:.1%} of the LED's "
            f"power (normal incidence; filter: {document['setup']['excitation_filter'].split(':')[0]}; "
            f"spectrum: {document['setup']['led_spectrum']})"
        )
    out.print(f"maps and illumination.json in {out_dir}")


def _check_optimize_options(
    max_cv: float, rays: int, samples: int, rounds: int, workers: int, files: tuple[Path | None, ...]
) -> None:
    """A UserError for an option of ``cm2 illum optimize`` out of range or an input file that is missing."""
    if not 0 < max_cv < 1:
        raise UserError(f"--max-cv = {max_cv}: must lie within 0–1")
    if rays < 1000:
        raise UserError(f"--rays = {rays}: must be ≥ 1000")
    if samples < 2 or rounds < 0 or workers < 1:
        raise UserError("--samples must be ≥ 2, --rounds ≥ 0, --workers ≥ 1")
    for path in files:
        if path is not None and not path.is_file():
            raise UserError(f"{path}: no such file")


def _optimize_gradient(
    preset: str,
    rays: int,
    max_cv: float,
    seed: int,
    files: tuple[Path | None, ...],
    iterations: int,
    learning_rate_um: float,
    step_rule: str,
    free_aim: bool,
    out_dir: Path,
    overwrite: bool,
    as_json: bool,
) -> None:
    """``cm2 illum optimize --method gradient``: check its options, run the search, print the summary."""
    from cm2optics.design import load_preset
    from cm2optics.illumination.gradient_search import STEP_RULES, optimize_lens_gradient
    from cm2optics.optics.backend import is_jit, mitsuba

    if step_rule not in STEP_RULES:
        raise UserError(f"--step-rule {step_rule}: must be one of {', '.join(STEP_RULES)}")
    if free_aim:
        raise UserError("--method gradient optimises the lens's Zernike terms only: --free-aim needs --method sweep")
    if iterations < 2:
        raise UserError(f"--iterations = {iterations}: must be ≥ 2")
    if not (math.isfinite(learning_rate_um) and 0 < learning_rate_um <= 15):
        raise UserError(f"--learning-rate-um = {learning_rate_um}: must lie within 0–15 µm")
    design = load_preset(preset)
    if design.collimator is None:
        raise UserError(f"design {design.name!r} has no collimator to optimise (use a preset with one, e.g. cm2-v2)")
    mitsuba()
    if not is_jit():
        raise UserError(
            "--method gradient needs Dr.Jit's LLVM or CUDA variant (no LLVM ≥ 17 found: see DRJIT_LIBLLVM_PATH)"
        )
    output_folder(out_dir, "illum optimize", inputs=[preset, *[f for f in files if f]], overwrite=overwrite)
    inputs = tuple(str(f.resolve()) if f else None for f in files)
    result = optimize_lens_gradient(
        design,
        out_dir,
        rays=rays,
        iterations=iterations,
        learning_rate_um=learning_rate_um,
        max_cv=max_cv,
        seed=seed,
        step_rule=step_rule,
        inputs=inputs,
        show_progress=not as_json,
    )
    _echo_optimized(
        result,
        as_json,
        lambda verdict: (
            f"gradient: {result['rays_traced']} rays traced in {iterations} steps; built part: delivered "
            f"{result['delivered_fraction']:.1%} ± {result['delivered_fraction_stderr']:.2%}, CV "
            f"{result['uniformity_cv']:.1%} ({verdict} CV ≤ {max_cv:.0%}); collimator printable: "
            f"{result['printability']['printable']}"
        ),
    )


def _echo_optimized(summary: dict[str, Any], as_json: bool, line: Any) -> None:
    """Print an optimisation's summary: as JSON, or as a table and the one-line verdict
    ``line(verdict)`` (verdict: whether the design meets the CV limit)."""
    if as_json:
        print(json.dumps(summary, indent=2, ensure_ascii=False))
        return
    out.print_json(json.dumps(summary, ensure_ascii=False))
    out.print(line("meets" if summary["meets_uniformity"] else "does NOT meet"))


@illum_app.command("optimize")
@user_errors
def optimize(
    preset: PresetOption = "cm2-v2",
    rays: Annotated[int, typer.Option("--rays", "-n", help="LED rays per candidate (all LEDs).")] = 200_000,
    max_cv: Annotated[
        float, typer.Option("--max-cv", help="Uniformity constraint: coefficient of variation inside the circle (0–1).")
    ] = 0.10,
    samples: Annotated[int, typer.Option("--samples", help="Candidates of the first (space-filling) sweep.")] = 64,
    rounds: Annotated[int, typer.Option("--rounds", help="Refinement sweeps around the best feasible candidate.")] = 2,
    dask_address: Annotated[
        str | None,
        typer.Option("--dask-address", help="An existing Dask scheduler (tcp://host:8786); default: a local cluster."),
    ] = None,
    workers: Annotated[int, typer.Option("--workers", help="Workers of the local Dask cluster.")] = 2,
    seed: Annotated[int, typer.Option("--seed", help="Random seed of the sweep and of the traces.")] = 0,
    free_aim: Annotated[
        bool,
        typer.Option(
            "--free-aim",
            help="Sweep the LED units' tilt, offset, aim point (led_array.aim_mm) and azimuth too; units that "
            "enter the imaging tower are infeasible, and the chosen design passes the CAD interference check.",
        ),
    ] = False,
    freeform: Annotated[
        bool,
        typer.Option(
            "--freeform",
            help="Sweep the lens's Zernike terms too (collimator.lens_freeform_um, Noll 3, 4, 6, 7, 11, ±15 µm): "
            "the lens departs from revolution.",
        ),
    ] = False,
    fixed_profile: Annotated[
        bool,
        typer.Option(
            "--fixed-profile",
            help="Keep the design's collimator profile: sweep only the placement (--free-aim) and/or the "
            "freeform terms (--freeform) of the design given.",
        ),
    ] = False,
    cone_wall: Annotated[
        bool,
        typer.Option(
            "--cone-wall",
            help="Sweep the profile with a prescribed TIR wall (collimator.tir_cone_deg, "
            "tir_cone_curvature_per_mm, tir_max_radius_mm) around a cavity that encloses the LED at its mouth "
            "(led_gap_mm 0–0.1), instead of the wall designed for the LED's centre.",
        ),
    ] = False,
    tir_azimuthal: Annotated[
        bool,
        typer.Option(
            "--tir-azimuthal",
            help="Sweep the TIR wall's departure from revolution too (collimator.tir_cos2 ±0.2, tir_cos4 ±0.1: "
            "its radial departure from the entry ring scaled by 1 + c2 cos 2φ + c4 cos 4φ); walls that leave "
            "the square footprint are infeasible.",
        ),
    ] = False,
    led_profile: LedProfileOption = None,
    led_spectrum: LedSpectrumOption = None,
    filter_table: FilterTableOption = None,
    out_dir: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for the improved design YAML, its STL and the sweep table.")
    ] = Path("out/illum-opt"),
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
    method: Annotated[
        str,
        typer.Option(
            "--method",
            help="sweep: the Dask sweep; gradient: Adam on the lens's Zernike terms (Noll 3, 4, 6, 7, 11) with "
            "gradients through Dr.Jit (profile and placement kept; --rays per iteration).",
        ),
    ] = "sweep",
    iterations: Annotated[int, typer.Option("--iterations", help="Gradient steps (--method gradient).")] = 24,
    learning_rate_um: Annotated[
        float,
        typer.Option(
            "--learning-rate-um",
            help="Step of the Zernike terms, µm: Adam's per term, or the projected rule's first step length "
            "(--method gradient).",
        ),
    ] = 1.5,
    step_rule: Annotated[
        str,
        typer.Option(
            "--step-rule",
            help="adam: Adam on D − 2 max(0, CV′ − max CV), fresh rays every step, the mean of the second half's "
            "iterates; projected: gradient projection on dD with CV′ ≤ max CV a constraint, the same rays every "
            "step, a trust region, the best iterate (--method gradient).",
        ),
    ] = "adam",
    robust_samples: Annotated[
        int,
        typer.Option(
            "--robust-samples",
            help="Score every candidate on its expected delivered fraction and CV over this many drawn builds "
            "(the errors of cm2 illum robustness; the same builds for every candidate, seeded by --seed); "
            "0: on its nominal figures (--method sweep).",
        ),
    ] = 0,
    led_placement_um: LedPlacementOption = 50.0,
    unit_tilt_deg: UnitTiltOption = 1.0,
    surface_rms_um: SurfaceRmsOption = 2.0,
    min_sbr_interference: Annotated[
        float,
        typer.Option(
            "--min-sbr-interference",
            help="Least SBR of the interference-only emission chain, computed from each candidate's traced beam "
            "(its glow and the excitation a flat sample mirrors into the lenslets); 0: unconstrained (--method sweep).",
        ),
    ] = 0.0,
    min_sbr_hybrid: Annotated[
        float,
        typer.Option(
            "--min-sbr-hybrid",
            help="Least SBR of the hybrid chain (with the film), from each candidate's traced beam; 0: unconstrained.",
        ),
    ] = 0.0,
) -> None:
    """Search the collimator's parameters for the largest delivered fraction whose array
    uniformity (CV inside the circle) is ≤ --max-cv, as a parallel sweep on Dask, and write
    the best design (`design.yaml`, which rebuilds the part), its CAD collimator
    (`collimator.stl` and `.step`, the STL checked for printing: watertight, walls ≥
    mechanics.min_wall_mm), that part's own trace (`built_part`, maps in `irradiance.png`) and
    every candidate (`sweep.json`). Swept: lens angle, cavity radius, LED gap, entry wall, height,
    and the two sub-beams' output spreads and mapping exponents (collimator.lens_spread_deg …;
    zero spreads = the collimating cm2-v2 architecture); with --free-aim also the units' tilt,
    offset, aim point and azimuth (led_array.*), units that would enter the imaging tower being
    infeasible and the chosen design passing the CAD assembly's interference check
    (`assembly_interferences`). Reports beside it the étendue bound, the most any rotationally
    symmetric beam can deliver at that CV (`uniform_beam_bound`) and, with --free-aim, the same
    for re-aimed units and the finite LED (`free_aim_bound`); the bounds' spectral ceiling comes
    from --filter-table and --led-spectrum when given. With --robust-samples N every candidate is
    also traced as N built devices (LED placement, unit tilt and printer surface errors, drawn
    as cm2 illum robustness draws them, the same N for every candidate) and ranked on
    E[delivered] − 2 max(0, E[CV′] − max CV) (`robust` in the result). With --min-sbr-interference
    / --min-sbr-hybrid every candidate's SBR is computed from its traced beam and held to the floor,
    its score scaled by the shortfall (`sbr` in the result): a brighter aim may not buy its light with
    excitation mirrored into the lenslets.
    """
    from cm2optics.design import load_preset
    from cm2optics.illumination.optimize import RobustScoring, SBRFloor, optimize_collimator

    files = (led_profile, led_spectrum, filter_table)
    _check_optimize_options(max_cv, rays, samples, rounds, workers, files)
    if method not in ("sweep", "gradient"):
        raise UserError(f"--method {method}: must be sweep or gradient")
    if not 0 <= robust_samples <= 1000:
        raise UserError(f"--robust-samples = {robust_samples}: must lie within 0–1000")
    tolerances = _tolerances(led_placement_um, unit_tilt_deg, surface_rms_um)
    if method == "gradient" and robust_samples:
        raise UserError("--robust-samples scores the sweep's candidates: it needs --method sweep")
    for name, value in (("--min-sbr-interference", min_sbr_interference), ("--min-sbr-hybrid", min_sbr_hybrid)):
        if not (math.isfinite(value) and value >= 0):
            raise UserError(f"{name} = {value}: must be a finite number ≥ 0")
    sbr_floor = SBRFloor(min_sbr_interference, min_sbr_hybrid) if min_sbr_interference or min_sbr_hybrid else None
    if method == "gradient" and sbr_floor is not None:
        raise UserError("--min-sbr-interference/--min-sbr-hybrid hold the sweep's candidates: they need --method sweep")
    if method == "gradient":
        _optimize_gradient(
            preset,
            rays,
            max_cv,
            seed,
            files,
            iterations,
            learning_rate_um,
            step_rule,
            free_aim,
            out_dir,
            overwrite,
            as_json,
        )
        return
    if fixed_profile and not (free_aim or freeform or tir_azimuthal):
        raise UserError("--fixed-profile leaves nothing to sweep: add --free-aim, --freeform and/or --tir-azimuthal")
    if fixed_profile and cone_wall:
        raise UserError("--cone-wall sweeps the profile: it cannot go with --fixed-profile")
    design = load_preset(preset)
    check_dask_address(dask_address)
    output_folder(out_dir, "illum optimize", inputs=[preset, *[f for f in files if f]], overwrite=overwrite)
    search = {"rays": rays, "max_cv": max_cv, "samples": samples, "rounds": rounds, "seed": seed}
    inputs = tuple(str(f.resolve()) if f else None for f in files)
    result = optimize_collimator(
        design,
        out_dir,
        **search,
        dask_address=dask_address,
        workers=workers,
        show_progress=not as_json,
        free_aim=free_aim,
        inputs=inputs,
        freeform=freeform,
        fixed_profile=fixed_profile,
        cone_wall=cone_wall,
        robust=RobustScoring(robust_samples, tolerances, seed) if robust_samples else None,
        sbr_floor=sbr_floor,
        tir_azimuthal=tir_azimuthal,
    )
    summary = {k: v for k, v in result.items() if k != "candidates"}  # every candidate is in sweep.json
    _echo_optimized(
        summary,
        as_json,
        lambda verdict: (
            f"best: delivered {summary['delivered_fraction']:.1%} ± {summary['delivered_fraction_stderr']:.2%}, "
            f"CV {summary['uniformity_cv']:.1%} ({verdict} CV ≤ {max_cv:.0%}); étendue/filter bound "
            f"{summary['etendue_bound']['delivered_bound']:.1%}; best symmetric beam at this CV "
            f"{summary['uniform_beam_bound']['delivered_bound']:.1%}; collimator printable: "
            f"{summary['printability']['printable']}"
            + (
                ""
                if summary["base_plate_printable"] is None
                else f"; base plate printable: {summary['base_plate_printable']}"
            )
            + (
                ""
                if summary["sbr"] is None
                else f"; SBR of the traced beam {summary['sbr']['sbr_interference_only']:.3g} (interference only) / "
                f"{summary['sbr']['sbr_hybrid']:.4g} (hybrid), floor met: {summary['sbr']['meets_sbr']}"
            )
        ),
    )


@illum_app.command("robustness")
@user_errors
def robustness(
    preset: PresetOption = "cm2-v2",
    collimator: Annotated[
        Path | None,
        typer.Option("--collimator", help="A collimator STL (mm) to study instead of the design's own CAD part."),
    ] = None,
    led_position: Annotated[
        str | None,
        typer.Option("--led-position", help="Centre of the LED's emitting surface in the STL's frame, X,Y,Z mm."),
    ] = None,
    led_axis: Annotated[
        str | None, typer.Option("--led-axis", help="Direction the LED emits in, in the STL's frame, X,Y,Z.")
    ] = None,
    samples: Annotated[int, typer.Option("--samples", help="Monte Carlo samples (≥ 2).")] = 32,
    rays: Annotated[int, typer.Option("--rays", "-n", help="LED rays per sample, split over the LEDs.")] = 200_000,
    led_placement_um: LedPlacementOption = 50.0,
    unit_tilt_deg: UnitTiltOption = 1.0,
    surface_rms_um: SurfaceRmsOption = 2.0,
    max_cv: Annotated[float, typer.Option("--max-cv", help="Uniformity limit counted in the report (0–1).")] = 0.10,
    led_profile: LedProfileOption = None,
    led_spectrum: LedSpectrumOption = None,
    filter_table: FilterTableOption = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the drawn errors and of the traces.")] = 0,
    out_dir: Annotated[Path, typer.Option("--out", "-o", help="Folder for robustness.json and robustness.png.")] = Path(
        "out/illum-robustness"
    ),
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Monte Carlo of the built design under manufacturing and assembly errors: every LED moved
    in its plane (± --led-placement-um), every unit tilted (± --unit-tilt-deg about two axes),
    every collimator's surface moved by a smooth random field of --surface-rms-um RMS (its exit
    face kept), each drawn independently per unit and sample. Reports the as-designed figures
    and the delivered fraction and CV as mean ± sd over the samples (every sample traces the
    same LED rays; the CV also without each trace's Monte Carlo noise floor), and the share
    of samples within --max-cv. The same seed gives the same
    numbers. --json prints the report (robustness.json) without per-sample rows.
    """
    import numpy as np

    from cm2optics.design import load_preset
    from cm2optics.formats.atomic import write_json_atomic
    from cm2optics.illumination.compare import setup_from_options, stl_collimator
    from cm2optics.illumination.geometry import build_scene, collimator_from_design
    from cm2optics.illumination.robustness import robustness_study, write_robustness_png
    from cm2optics.optics.backend import mitsuba
    from cm2optics.progress import progress_bar

    if samples < 2 or samples > 10_000:
        raise UserError(f"--samples = {samples}: must lie within 2–10000")
    if rays < 1000 or rays > 100_000_000:
        raise UserError(f"--rays = {rays}: must lie within 1000–100000000")
    if not 0 < max_cv < 1:
        raise UserError(f"--max-cv = {max_cv}: must lie within 0–1")
    tolerances = _tolerances(led_placement_um, unit_tilt_deg, surface_rms_um)
    files = (collimator, led_profile, led_spectrum, filter_table)
    for path in files:
        if path is not None and not path.is_file():
            raise UserError(f"{path}: no such file")
    design = load_preset(preset)
    if collimator is None and (led_position is not None or led_axis is not None):
        raise UserError("--led-position/--led-axis place the LED in an STL: give the STL with --collimator")
    check_output(out_dir, command="illum robustness", kind="folder", inputs=[preset, *files], overwrite=overwrite)
    vector = {"n": 3, "example": "0,0,1"}
    if collimator is not None:
        position = parse_float_list(led_position, name="--led-position", **vector) or (0.0, 0.0, 0.0)
        axis = parse_float_list(led_axis, name="--led-axis", **vector) or (0.0, 0.0, 1.0)
        part = stl_collimator(design, collimator, np.array(position, float), np.array(axis, float))
    elif design.collimator is None:
        raise UserError(f"design {design.name!r} has no collimator: give one with --collimator")
    else:
        part = collimator_from_design(design)
    setup = setup_from_options(
        design, led_profile=led_profile, led_spectrum=led_spectrum, filter_table=filter_table, rays=rays, seed=seed
    )
    try:
        scene = build_scene(design, part)
    except ValueError as error:
        raise UserError(str(error)) from None
    output_folder(out_dir, "illum robustness", inputs=[preset, *files], overwrite=overwrite)
    mitsuba()
    with progress_bar("[bold]robustness[/] {task.description}", enabled=not as_json) as bar:
        task = bar.add_task(part.label, total=samples + 1)
        study = robustness_study(scene, setup, tolerances, samples, seed, lambda: bar.advance(task), max_cv)
    study["setup"] = {"preset": design.name, "parameter_hash": design.parameter_hash(), **setup.notes}
    write_json_atomic(out_dir / "robustness.json", study)
    write_robustness_png(study, out_dir / "robustness.png")
    summary = {k: v for k, v in study.items() if k != "per_sample"}
    if as_json:
        print(json.dumps(summary, indent=2, ensure_ascii=False))
        return
    nominal, delivered, cv = study["nominal"], study["delivered_fraction"], study["uniformity_cv_corrected"]
    out.print(
        f"{part.label}: as designed delivered {nominal['delivered_fraction']:.3f} ± "
        f"{nominal['delivered_fraction_stderr']:.3f}, CV {nominal['uniformity_cv_corrected']:.1%}; under errors "
        f"({samples} samples) delivered {delivered['mean']:.3f} ± {delivered['sd']:.3f}, CV {cv['mean']:.1%} ± "
        f"{cv['sd']:.1%}; {study['share_within_max_cv']:.0%} of samples at CV ≤ {max_cv:.0%} (CVs without "
        "their Monte Carlo noise floor)"
    )
    out.print(f"robustness.json and robustness.png in {out_dir}")
