"""``cm2 calibrate``: compare a model with measured data, name the effects it lacks, correct it.

Registered by :mod:`cm2optics.cli`; the work is :func:`cm2optics.calibrate.scan.calibrate_scan`
(a PSF scan) and :func:`cm2optics.calibrate.image.calibrate_image` (a beads frame), the reports
:func:`cm2optics.reports.calibrate.write_calibration_report` and
:func:`cm2optics.reports.calibrate_image.write_image_report`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from cm2optics.cli.options import JsonOption, OverwriteOption, PresetOption, check_output, user_errors

__all__ = ["calibrate_app"]

calibrate_app = typer.Typer(
    help="Close the loop with measured data: the residual of a model against a measurement, the physical "
    "effects that explain it (with values ± uncertainties), the corrected design, the error before and after.",
    no_args_is_help=True,
)


@calibrate_app.command("scan")
@user_errors
def scan(
    scan_dir: Annotated[Path, typer.Argument(help="Measured PSF scan folder (positions.csv, TIFFs, scan.yaml).")],
    preset: PresetOption = "cm2-v2",
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")] = Path("out/calibration"),
    fit_positions: Annotated[
        int, typer.Option("--fit-positions", min=3, help="Positions traced for the attribution, spread over the grid.")
    ] = 27,
    max_effects: Annotated[int, typer.Option("--max-effects", min=1, max=12, help="Effects kept at most.")] = 6,
    workers: Annotated[
        int,
        typer.Option(
            "--workers",
            min=1,
            max=64,
            help="Processes tracing the model at every scan position (above 1: beside the attribution and "
            "the analysis, at a lower priority).",
        ),
    ] = 1,
    source_um: Annotated[
        float | None,
        typer.Option(
            "--source-um",
            min=0,
            help="Calibration source diameter as declared, µm (default: scan.yaml's, else a point); the "
            "source_size effect fits a larger one.",
        ),
    ] = None,
    source_profile: Annotated[
        str | None,
        typer.Option(
            "--source-profile",
            help="Calibration source's angular profile: isotropic, lambertian, cos^M or "
            "'gaussian, 1/e^2 half-angle A deg' (default: scan.yaml's source_profile, else isotropic).",
        ),
    ] = None,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Calibrate a design against a measured PSF scan taken on it.

    Traces the design at the scan's positions with the calibration source scan.yaml records
    (source_diameter_um, source_profile; --source-um/--source-profile override; none recorded:
    isotropic, with a warning), registers it to the data (one frame offset, flux scale, dark
    level), estimates the sensor's noise (read noise from the dark regions, the quantisation
    step from the recorded values; the gain from scan.yaml's counts_per_electron, else from the
    data; a scan whose scan.yaml says noise: none has its noise scale profiled out), then names
    the effects of the library (MLA decentre, rotation, spacing, lenslet pitch, single-lenslet
    decentre and transmission, source profile, source size, stray light, leakage, crosstalk, vignetting) that
    the residual asks for, by the BIC, with joint refits and 1σ uncertainties. Effects that move
    or dim lenslets are applied to the traced foci (their effective PSFs resampled) and traced
    exactly once the fit settles; spacing, vignetting and the source profile are linearised and
    re-traced. Writes calibration.json, corrected-design.yaml (passes cm2 design validate),
    residual and field-map figures and report.html into --out. JSON keys include effects,
    nmse_before, nmse_after, chi2_before, chi2_after, unexplained and warnings.

    What the effects leave above the noise is described in unexplained (lenslets, field_mm,
    depths_mm, energy_fraction, description: a ghost, a position-dependent loss, …) and a
    non-physical low-rank correction of the foci is fitted to it: JSON key correction
    (physical: false, its error on positions held out of its fit), lowrank-correction.npz.

    Problems of the data rather than the optics are named, not fitted: defective sensor pixels
    (hot, dead, stuck; clusters, columns) are found in the frames themselves, left out of the
    fit and listed (JSON key sensor_defects); a source or exposure drift along the acquisition
    order, frames whose foci are displaced together (stage backlash, position errors), a z scale
    error of the stage (the foci's spread against depth) and a smooth gain over the sensor (an
    uncorrected flat field: JSON key sensor_gain) are named in warnings.

    Validated on traced 3×3×2 scans (8× binning, shot + read noise): an undeclared 0.5° MLA
    rotation and a lenslet at 60 % transmission are named alone and measured within 0.001,
    a clean scan yields no effect (BENCHMARKS.md, issue 14).
    """
    from cm2optics.calibrate.scan import calibrate_scan
    from cm2optics.design import load_preset
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.reports.calibrate import write_calibration_report

    design = load_preset(preset)
    check_output(out, command="calibrate scan", kind="folder", inputs=[scan_dir, preset], overwrite=overwrite)
    say = (lambda message: None) if as_json else (lambda message: typer.echo(message, err=True))
    result = calibrate_scan(
        scan_dir,
        design,
        fit_positions=fit_positions,
        max_effects=max_effects,
        source_diameter_um=source_um,
        source_profile=source_profile,
        workers=workers,
        progress=say,
    )
    claim_folder(out, "calibrate scan")
    report = write_calibration_report(result, out)
    doc = result.document
    if as_json:
        print(json.dumps({k: v for k, v in doc.items() if k not in ("before", "after")}, indent=2, ensure_ascii=False))
        return
    _echo_fit(doc)
    if "correction" in doc:
        held = doc["correction"]["held_out"]
        typer.echo(
            f"  low-rank correction (non-physical), held-out NMSE {held['nmse_before']:.4g} → {held['nmse_after']:.4g}"
        )
    typer.echo(f"report: {report}")


@calibrate_app.command("image")
@user_errors
def image(
    frame: Annotated[
        Path,
        typer.Argument(
            help="Measured beads frame (.tif or .npy; its YAML sidecar gives bit_depth, exposure_ms and "
            "noise.counts_per_electron, the camera's gain)."
        ),
    ],
    emitters: Annotated[
        Path,
        typer.Option("--emitters", help="Reference emitters CSV (x_um, y_um, z_um, diameter_um, intensity)."),
    ],
    preset: PresetOption = "cm2-v2",
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")] = Path("out/calibration-image"),
    scan_report: Annotated[
        Path | None,
        typer.Option(
            "--scan-report", help="Take the effects of this `cm2 calibrate scan` report instead of fitting the frame."
        ),
    ] = None,
    max_effects: Annotated[int, typer.Option("--max-effects", min=1, max=12, help="Effects kept at most.")] = 6,
    rank: Annotated[int, typer.Option("--rank", min=1, max=64, help="Rank of the reconstructions' LSV models.")] = 8,
    max_iter: Annotated[int, typer.Option("--max-iter", min=1, help="FISTA iterations at most.")] = 60,
    l1: Annotated[float, typer.Option("--l1", min=0, help="FISTA's ℓ1 weight, relative to ‖Aᵀb‖∞.")] = 0.02,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Calibrate a design against a measured frame of beads at known positions, and report what
    the correction does to the reconstruction.

    The model's frame is the sum of the traced images of the reference emitters (the design at
    the frame's binning, found from its size; one bead diameter, the CSV's median; intensities
    from the CSV). The scan loop's attribution names the library effects the frame's residual
    asks for, with values ± 1σ (or --scan-report takes a previous `cm2 calibrate scan`'s). The
    frame is then reconstructed by FISTA with 3D-LSV models built from the traced single-source
    images of the nominal and of the corrected design around the beads, and each volume scored
    against the emitters at its own F1-optimal threshold. Writes calibration.json,
    corrected-design.yaml, the detections before/after (TP/FP/FN on MIPs), the residual maps
    and report.html into --out. JSON keys: effects, nmse_before/after, chi2_before/after,
    unexplained (as `cm2 calibrate scan`), recall_/precision_/f1_/n_tp_/n_fp_/n_fn_/
    rmse_lateral_um_/rmse_axial_um_ before and after.
    """
    import numpy as np

    from cm2optics.calibrate.image import BeadsFrame, calibrate_image, check_frame, frame_binning, scan_report_effects
    from cm2optics.calibrate.tracer import TracerSimulator
    from cm2optics.design import load_preset
    from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind
    from cm2optics.formats.emitters import read_emitters
    from cm2optics.formats.measurement import read_measurement, read_sidecar
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.recon.reconstruct import ReconOptions
    from cm2optics.reports.calibrate_image import write_image_report

    design = load_preset(preset)
    inputs = [frame, emitters, preset] + ([scan_report] if scan_report else [])
    check_output(out, command="calibrate image", kind="folder", inputs=inputs, overwrite=overwrite)
    counts = read_measurement(frame)
    meta = read_sidecar(frame) or {}
    table = read_emitters(emitters)
    noise = meta.get("noise") or {}
    beads = BeadsFrame(
        counts,
        table,
        float(meta.get("exposure_ms", 1.0)),
        int(meta.get("bit_depth", 16)),
        frame.name,
        noise.get("counts_per_electron"),
    )
    binning = frame_binning(counts.shape, design)
    check_frame(beads, design)
    effects = scan_report_effects(scan_report) if scan_report else None
    diameter = float(np.median(table.diameter_um)) if len(table) else 0.0
    simulator = TracerSimulator(design, binning, PointSource(diameter, AngularProfile(ProfileKind.ISOTROPIC)))
    say = (lambda message: None) if as_json else (lambda message: typer.echo(message, err=True))
    result = calibrate_image(
        beads,
        design,
        simulator,
        binning=binning,
        effects=effects,
        max_effects=max_effects,
        rank=rank,
        recon_options=ReconOptions(max_iter=max_iter, l1=l1),
        progress=say,
    )
    claim_folder(out, "calibrate image")
    report = write_image_report(result, out)
    doc = result.document
    if as_json:
        print(json.dumps(doc, indent=2, ensure_ascii=False))
        return
    _echo_fit(doc)
    typer.echo(
        f"F1 {doc['f1_before']:.3f} → {doc['f1_after']:.3f} (recall {doc['recall_before']:.3f} → "
        f"{doc['recall_after']:.3f}, precision {doc['precision_before']:.3f} → {doc['precision_after']:.3f}; "
        f"FP {doc['n_fp_before']} → {doc['n_fp_after']})"
    )
    typer.echo(f"report: {report}")


@calibrate_app.command("illumination")
@user_errors
def illumination(
    map_tif: Annotated[Path, typer.Argument(help="Measured map: a 2-D TIFF of a uniform fluorescent slide (counts).")],
    pixel_um: Annotated[float, typer.Option("--pixel-um", help="The map's pixel on the sample, µm.")],
    preset: PresetOption = "cm2-v2",
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")] = Path("out/calibration-illumination"),
    rays: Annotated[int, typer.Option("--rays", help="Rays of each model trace (all LEDs), ≥ 1000.")] = 400_000,
    bin_mm: Annotated[float, typer.Option("--bin-mm", help="Pitch of the comparison grid on the sample, mm.")] = 0.5,
    counts_per_electron: Annotated[
        float, typer.Option("--counts-per-electron", help="The camera's gain, for the map's shot noise.")
    ] = 1.0,
    max_effects: Annotated[int, typer.Option("--max-effects", min=1, max=12, help="Effects kept at most.")] = 4,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the model's rays.")] = 0,
    polish_rays: Annotated[
        int | None,
        typer.Option(
            "--polish-rays",
            help="Rays of the final refit when a tilt or decentre is kept (default 4 × --rays; 0: none).",
        ),
    ] = None,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Calibrate a design's illumination against a measured map.

    The map's rows run along +y and its columns along +x of the device frame (as cm2 illum
    run's maps), its centre near the optical axis. It is averaged at the centres of a grid of
    pitch --bin-mm over the field, under a tent (bilinear) kernel one pitch wide each side; the
    design is traced as cm2 illum run traces it (with its illumination_as_built), its rays
    shared among the centres by the same kernel, and registered to it (one global scale, one lateral offset up to 0.5 mm); the residual's χ²
    counts the map's shot noise and the model's Monte Carlo noise. Effects named by the BIC,
    refitted with the tracer in the loop, with 1σ uncertainties: led_flux (each LED's flux
    relative to the others), led_tilt (a unit tilted, degrees), collimator_decenter (mm). A tilt
    or decentre is kept only if it also lowers the BIC, on average, on 8 model traces with
    independent rays by 3σ of that mean's noise; kept ones are refitted last with --polish-rays.
    Writes calibration.json, corrected-design.yaml (passes cm2 design validate), maps.png,
    profiles.png and report.html into --out. JSON keys include effects, nmse_before,
    nmse_after, chi2_before, chi2_after, unexplained, registration, uniformity_cv and
    radial_profile.
    """
    from cm2optics.calibrate.illumination import calibrate_illumination, read_measured_map
    from cm2optics.design import load_preset
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.reports.calibrate_illumination import write_illumination_calibration_report

    design = load_preset(preset)
    check_output(out, command="calibrate illumination", kind="folder", inputs=[map_tif, preset], overwrite=overwrite)
    image = read_measured_map(map_tif)
    say = (lambda message: None) if as_json else (lambda message: typer.echo(message, err=True))
    result = calibrate_illumination(
        image,
        pixel_um,
        design,
        bin_mm=bin_mm,
        rays=rays,
        seed=seed,
        counts_per_electron=counts_per_electron,
        max_effects=max_effects,
        label=str(map_tif),
        progress=say,
        polish_rays=polish_rays,
    )
    claim_folder(out, "calibrate illumination")
    report = write_illumination_calibration_report(result, out)
    doc = result.document
    if as_json:
        print(json.dumps(doc, indent=2, ensure_ascii=False))
        return
    _echo_fit(doc)
    typer.echo(f"report: {report}")


@calibrate_app.command("paper")
@user_errors
def paper(
    preset: PresetOption = "cm2-v2",
    out: Annotated[Path, typer.Option("--out", "-o", help="Report folder.")] = Path("out/calibration-paper"),
    rays: Annotated[int, typer.Option("--rays", help="Rays of each trace (all LEDs), ≥ 10000.")] = 400_000,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the rays.")] = 0,
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """The paper's own measurements as residuals of the model: (a) the excitation power, (b) the
    hybrid filter's SBR gain, (c) the de-magnification and the calibration source's edge drop.

    The paper measured up to 75 mW over the 8-mm field at 350 mA; the design is traced as cm2
    illum run traces it, and its power multiplied by a chain of factors, each with its value, 1σ
    relative uncertainty, source and whether the code computed it (LED photometric conversion
    from the spectrum and CIE V(λ), the power meter's aperture and angular response at the
    traced rays' incidence, the printed surface error by re-traces) or assumed it (thermal
    droop, the filter's coating); what remains is the unexplained ratio. The paper's numbers
    are inputs with their place in shared/paper. (b) models the bead phantom per pixel: a bead's
    peak against the leakage, the beads' own light in their foci's wings and the resin's
    autofluorescence, with and without the film (assumed parameters with ranges). (c) traces the
    central focus for a source stepped across the field: magnification (first order, traced,
    the MLA–sensor spacing for the paper's 4.15-µm pixel) and the energy drop, with the source
    half-angle that reproduces the paper's 85 %. Writes paper.json, excitation_power.png,
    sbr_phantom.png, edge_drop.png and report.html into --out. JSON keys: excitation_power
    (measured_mw, predicted_mw, factors, explained_mw, remaining_ratio, description), sbr_gain
    (gain, gain_by_terms, gain_range, sbr, leakage_factor_for_measured_gain, description),
    magnification (traced_magnification, chief_ray_magnification, paper_magnification,
    mla_to_sensor_for_paper_mm, description), edge_drop (relative_energy_*,
    source_profile_half_angle_deg, description).
    """
    from cm2optics.calibrate.paper import excitation_power_chain, trace_design
    from cm2optics.calibrate.paper_field import field_residuals
    from cm2optics.calibrate.paper_sbr import phantom_sbr
    from cm2optics.design import load_preset
    from cm2optics.errors import UserError
    from cm2optics.formats.outputs import claim_folder
    from cm2optics.reports.calibrate_paper import write_paper_report

    design = load_preset(preset)
    if design.collimator is None or design.absorption_filter is None:
        raise UserError(
            f"--preset {preset}: the paper's measurements are of a design with collimators and a hybrid filter (cm2-v2)"
        )
    if rays < 10_000:
        raise UserError(f"--rays = {rays}: must be ≥ 10000")
    check_output(out, command="calibrate paper", kind="folder", inputs=[preset], overwrite=overwrite)
    from cm2optics.illumination.traced_sbr import traced_excitation

    traced = trace_design(design, rays=rays, seed=seed)  # (a) and (b) read the same traced beam
    document = {
        "excitation_power": excitation_power_chain(design, rays=rays, seed=seed, traced=traced),
        "sbr_gain": phantom_sbr(design, traced_excitation(traced[2])),
        **field_residuals(design),
    }
    claim_folder(out, "calibrate paper")
    report = write_paper_report(document, out)
    if as_json:
        print(json.dumps(document, indent=2, ensure_ascii=False))
        return
    power = document["excitation_power"]
    typer.echo(f"excitation power: traced {power['predicted_mw']:.0f} mW, measured {power['measured_mw']:g} mW")
    for factor in power["factors"]:
        typer.echo(f"  {factor['name']}: × {factor['value']:.3f} ± {100 * factor['uncertainty']:.0f} %")
    typer.echo(f"  {power['description']}")
    for key, title in (("sbr_gain", "SBR gain"), ("magnification", "magnification"), ("edge_drop", "edge drop")):
        typer.echo(f"{title}: {document[key]['description']}")
    typer.echo(f"report: {report}")


def _echo_fit(doc: dict) -> None:
    """The lines every calibration prints: error before → after, the effects, what is unexplained."""
    typer.echo(
        f"NMSE {doc['nmse_before']:.4g} → {doc['nmse_after']:.4g}, χ² {doc['chi2_before']:.3g} → {doc['chi2_after']:.3g}"
    )
    for effect in doc["effects"]:
        unit = f"[{effect['unit']}]" if "unit" in effect else ""
        typer.echo(f"  {effect['name']}{unit}: {effect['parameters']} ± {effect['uncertainties']}")
    for item in doc["unexplained"]:
        typer.echo(f"  unexplained: {item['description']}")
