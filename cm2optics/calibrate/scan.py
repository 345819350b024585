"""Calibrate a design against a measured PSF scan: residual before, effects found, residual after.

:func:`calibrate_scan` is what ``cm2 calibrate scan`` runs:

1. the scan is read and checked against the design (sensor size at the scan's binning, pixel
   pitch, magnification within 10 %);
2. the design is traced at a spread subset of the scan's positions (``fit_positions``; all of
   them for small scans), their frames are checked (magnification, saturated or empty frames)
   and the attribution (:mod:`.attribute`) names the effects the residual asks for, with values
   and uncertainties;
3. the nominal and the corrected model are traced at every position and compared with the data
   (:mod:`.residual`): NMSE and χ² before and after, per image and per focus. With ``workers``
   processes, the nominal trace runs beside the attribution and the corrected one beside the
   analysis of the nominal: the process that waits on them keeps a core;
4. what the effects leave unexplained, where the remaining misfit is above the noise, is
   described by its signature (lenslets, field, depths, share of the energy) instead of being
   forced into a physical fit.

The corrected design (``as_built`` values and the MLA–sensor spacing) is returned with the
document; the frame offset is the scan's own (its stage origin and the sensor's placement are
not told apart) and stays out of the design.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from warnings import catch_warnings, simplefilter

import numpy as np

from cm2optics.calibrate.acquisition import (
    bright_foci,
    flux_drift,
    frame_flux_errors,
    spread_rate_per_mm,
    stage_errors,
    stage_xy_map,
    stage_z_scale,
)
from cm2optics.calibrate.attribute import Attribution, Problem, attribute
from cm2optics.calibrate.background import BackgroundStructure, background_entry, background_structure
from cm2optics.calibrate.defects import defective_pixels, describe_defects, fill_defects
from cm2optics.calibrate.effects import apply_image_effects, library, split_key
from cm2optics.calibrate.fixed_pattern import describe_fixed_pattern, fixed_pattern
from cm2optics.calibrate.lowrank_correction import LowRankCorrection, fit_correction, held_out_error
from cm2optics.calibrate.residual import CalibrationError, ResidualAnalysis, ScanData, analyse_scan, check_frames
from cm2optics.calibrate.sensor_gain import describe_sensor_gain, sensor_gain
from cm2optics.calibrate.tracer import (
    TracerSimulator,
    design_with,
    fitted_source,
    lenslet_vertices_px,
    submit_rates,
    tracing_pool,
)
from cm2optics.calibrate.unexplained import PATCH_HALF_PX, describe_unexplained
from cm2optics.design import SystemDesign
from cm2optics.emission.source import AngularProfile, PointSource
from cm2optics.formats.scan import PSFScan, grid_index, read_scan

__all__ = ["ScanCalibration", "calibrate_scan", "corrected_design", "effects_document", "fit_subset"]

#: A scan whose foci spread differs from the design's by more than this was taken on another design.
MAGNIFICATION_TOLERANCE = 0.10

Progress = Callable[[str], None]


@dataclass(frozen=True)
class ScanCalibration:
    """The result: the JSON document, both analyses, the attribution and the corrected design."""

    document: dict[str, Any]
    before: ResidualAnalysis
    after: ResidualAnalysis
    attribution: Attribution
    corrected_design: SystemDesign
    correction: LowRankCorrection | None = None


def _check_scan(scan: PSFScan, design: SystemDesign) -> None:
    """Clear errors for a scan that cannot have been taken on ``design``."""
    binning = scan.meta.binning
    expected = (design.sensor.height_px // binning, design.sensor.width_px // binning)
    if scan.images.shape[-2:] != expected:
        raise CalibrationError(
            f"wrong sensor size: the scan's images are {scan.images.shape[-2]} × {scan.images.shape[-1]} px, "
            f"the design's sensor ({design.sensor.name}) binned {binning}× gives {expected[0]} × {expected[1]} px"
        )


def _spread_px(centroids: np.ndarray) -> float:
    """Median distance (px) of the foci from their images' mean focus position (NaN: none)."""
    with catch_warnings():
        simplefilter("ignore", RuntimeWarning)  # an image without foci is a NaN, not a warning
        mean = np.nanmean(centroids, axis=1, keepdims=True)
        return float(np.nanmedian(np.linalg.norm(centroids - mean, axis=-1)))


def _check_magnification(before: ResidualAnalysis) -> None:
    """The foci's spread in the data against the model's, over the bright foci of the frames
    used: beyond 10 %, another design."""
    bright = bright_foci(before)[before.used]
    data = np.where(bright[..., None], before.data.centroid_px[before.used], np.nan)
    model = np.where(bright[..., None], before.model.centroid_px[before.used], np.nan)
    ratio = _spread_px(data) / max(_spread_px(model), 1e-9)
    if np.isfinite(ratio) and abs(ratio - 1.0) > MAGNIFICATION_TOLERANCE:
        raise CalibrationError(
            f"the scan's foci spread {ratio:.2f}× as far as the design's (more than "
            f"{MAGNIFICATION_TOLERANCE:.0%} off): was the scan taken on another design (MLA, spacing, binning)?"
        )


def fit_subset(positions_mm: np.ndarray, count: int) -> np.ndarray:
    """Indices of at most ``count`` positions spread over the scan's grid: the first, middle and
    last node of each axis (3 × 3 × 3), or every position when the scan is that small."""
    if len(positions_mm) <= count:
        return np.arange(len(positions_mm))
    index = grid_index(positions_mm)
    keep = np.ones(len(positions_mm), bool)
    for axis in range(3):
        nodes = np.unique(index[:, axis])
        chosen = nodes[np.unique(np.round(np.linspace(0, len(nodes) - 1, 3)).astype(int))]
        keep &= np.isin(index[:, axis], chosen)
    picked = np.flatnonzero(keep)
    return picked[np.round(np.linspace(0, len(picked) - 1, min(count, len(picked)))).astype(int)]


def _usable_subset(data: ScanData, simulator: TracerSimulator, subset: np.ndarray, gain: float | None) -> np.ndarray:
    """The fit positions ``subset`` less those left out of every fit (saturated, without light),
    from an analysis of their frames alone against the nominal model (traced here; the
    attribution re-uses the trace); a scan taken on another design is refused here, before the
    attribution, and again on the whole scan."""
    frames = data.subset(subset)
    positions = data.positions_mm[subset]
    rate = simulator.rates(positions, {})
    centres = simulator.focus_centres_px(positions)
    analysis = analyse_scan(frames, rate, positions, centres, simulator.pitch_px(), counts_per_electron=gain)
    _check_magnification(analysis)
    return subset[analysis.used]


def _without_defects(data: ScanData, simulator: TracerSimulator, subset: np.ndarray) -> tuple[ScanData, list[str]]:
    """``data`` with the sensor's defective pixels (:mod:`.defects`, found on the frames of
    ``subset`` against the nominal model there) marked and filled, and a warning naming them."""
    defects = defective_pixels(
        data.counts[subset], simulator.rates(data.positions_mm[subset], {}), data.exposure_ms[subset]
    )
    if not defects.any():
        return data, []
    found = describe_defects(defects)
    counts = fill_defects(data.counts, defects)
    where = ", ".join(
        part
        for part in (
            f"columns {found['columns']}" if found["columns"] else "",
            f"rows {found['rows']}" if found["rows"] else "",
            f"pixels (row, col) {found['other_pixels']}" if found["other_pixels"] else "",
        )
        if part
    )
    warning = (
        f"{found['pixels']} defective sensor pixels (hot, dead or stuck; {where}) are left out of the fit and "
        f"filled from their neighbours: a defect of the sensor, not of the optics"
    )
    filled = ScanData(counts, data.exposure_ms, data.positions_mm, data.files, data.bit_depth, defects)
    return filled, [warning]


def _with_image_effects(rate: np.ndarray, simulator: TracerSimulator, attribution: Attribution) -> np.ndarray:
    """The traced images of the corrected design with the fitted sensor-side effects applied
    (leakage as a uniform rate per unit flux)."""
    rate = apply_image_effects(rate, attribution.effects, simulator.pixel_um)
    leak = attribution.effects.get("leakage_background", {}).get("counts_per_ms", 0.0)
    return rate + np.float32(leak / max(attribution.registration.flux_scale, 1e-30))


def corrected_design(design: SystemDesign, attribution: Attribution) -> SystemDesign:
    """``design`` with every fitted effect written into its fields: the optical ones as the tracer
    reads them (:func:`~cm2optics.calibrate.tracer.design_with`), the sensor-side ones as
    ``as_built`` values; the calibration source's profile and size belong to the source, not the
    device (the document's ``source_corrected`` names the source found)."""
    changed = design_with(design, attribution.effects)
    effects = attribution.effects
    fields: dict[str, object] = {}
    if "stray_light" in effects:
        fields["as_built.stray_light_fraction"] = effects["stray_light"]["fraction"]
        fields["as_built.stray_light_width_um"] = effects["stray_light"]["width_um"]
    if "pixel_crosstalk" in effects:
        fields["as_built.pixel_crosstalk_fraction"] = effects["pixel_crosstalk"]["fraction"]
    if "leakage_background" in effects:
        fields["as_built.leakage_counts_per_ms"] = effects["leakage_background"]["counts_per_ms"]
    return changed.with_changes(fields) if fields else changed


def effects_document(attribution: Attribution) -> list[dict[str, Any]]:
    """Fitted effects in the report's vocabulary: ``{name, parameters, uncertainties}`` (a
    per-lenslet effect names its lenslet among the parameters, a per-side effect its side)."""
    out = []
    for key, parameters in attribution.effects.items():
        name, index = split_key(key)
        extra = {} if index is None else {"side" if isinstance(index, str) else "lenslet": index}
        out.append(
            {
                "name": name,
                "parameters": {**extra, **{k: round(float(v), 6) for k, v in parameters.items()}},
                "uncertainties": {k: float(f"{v:.3g}") for k, v in attribution.uncertainties.get(key, {}).items()},
            }
        )
    return out


def _summary(
    before: ResidualAnalysis,
    after: ResidualAnalysis,
    attribution: Attribution,
    problem: Problem,
    pixel_um: float,
    drifted: bool = False,
    background: BackgroundStructure | None = None,
) -> dict[str, Any]:
    """The report's headline keys: effects, NMSE and χ² before and after, what stays unexplained
    (a background structure as its own entry, the foci read above it)."""
    unexplained = describe_unexplained(
        after,
        pixel_um,
        per_frame=drifted,
        background=None if background is None else background.patches(after.model.centroid_px, PATCH_HALF_PX),
    )
    if background is not None:
        unexplained.append(background_entry(background, after, after.model.energy.shape[1]))
    return {
        "effects": effects_document(attribution),
        "nmse_before": round(before.nmse_total, 6),
        "nmse_after": round(after.nmse_total, 6),
        "chi2_before": round(before.chi2_total, 4),
        "chi2_after": round(after.chi2_total, 4),
        "unexplained": unexplained,
        "noise_model": "camera gain from scan.yaml" if problem.noise_known else "gain estimated from the data",
    }


#: A halo whose σ is under this many times the foci's own σ is a blur of the foci, not stray light.
NARROW_HALO = 3.0


def _widening_caveats(
    attribution: Attribution, source: PointSource, binning: int, after: ResidualAnalysis, pixel_um: float
) -> list[str]:
    """Caveats for the effects that only widen the foci as a blur common to every focus does: on
    foci a pixel or two wide, ``pixel_crosstalk`` (signal shared with the neighbouring pixels) and
    a ``stray_light`` halo not much wider than the foci themselves (σ under :data:`NARROW_HALO`
    times theirs, from the model's widths after the fit: an RMS radius √2·σ) widen every focus as
    a calibration source larger than declared does (its image, m·d across, blurs every focus
    alike), and the foci's widths do not tell them apart."""
    out = []
    declared = "a point" if source.diameter_um == 0 else f"{source.diameter_um:g} µm"
    alternative = (
        f"a calibration source larger than declared ({declared}) would (or any blur common to "
        f"every lenslet and depth): the source_size candidate, whose blur grows with the magnification over "
        f"depth, was tried beside it and not preferred, but on foci this narrow the two are close; check the "
        f"source's size (scan.yaml source_diameter_um) before reading it as"
    )
    crosstalk = attribution.effects.get("pixel_crosstalk")
    if crosstalk is not None:
        out.append(
            f"pixel_crosstalk ({crosstalk['fraction']:.3f} between the {binning}×-binned pixels) widens every focus "
            f"as {alternative} the sensor's"
        )
    halo = attribution.effects.get("stray_light")
    with catch_warnings():
        simplefilter("ignore", RuntimeWarning)
        focus_sigma_um = float(np.nanmedian(after.model.width_px[after.used])) / np.sqrt(2.0) * pixel_um
    if halo is not None and np.isfinite(focus_sigma_um) and halo["width_um"] < NARROW_HALO * focus_sigma_um:
        out.append(
            f"stray_light's halo (σ {halo['width_um']:.0f} µm) is barely wider than the foci themselves (σ "
            f"≈ {focus_sigma_um:.0f} µm): it widens every focus as {alternative} scattered light"
        )
    return out


def _fit_record(subset: np.ndarray, attribution: Attribution, problem: Problem) -> dict[str, Any]:
    """How the attribution went: the positions it traced, its steps, its registration."""
    return {
        "positions": [int(i) for i in subset],
        "steps": [
            {"added": s.added, "chi2_per_feature": round(s.chi2 / max(problem.n_features, 1), 4)}
            for s in attribution.steps
        ],
        "registration": attribution.registration.to_dict(),
        # the sensor's smooth gain, fitted as a nuisance beside the effects (attribute.FLAT_FIELD), or None
        "flat_field": None
        if attribution.flat_field is None
        else {k: round(float(v), 5) for k, v in attribution.flat_field.items()},
    }


def scan_source(
    extra: dict[str, Any], diameter_um: float | None = None, profile: str | None = None
) -> tuple[PointSource, list[str]]:
    """The calibration source a scan says it used (``source_diameter_um``, ``source_profile`` in
    its ``scan.yaml``), the arguments overriding them; with no profile anywhere, an isotropic
    point and a warning. A profile that cannot be read is a :class:`CalibrationError`."""
    warnings = []
    diameter = diameter_um if diameter_um is not None else extra.get("source_diameter_um", 0.0)
    text = profile if profile is not None else extra.get("source_profile")
    if text is None:
        text = "isotropic"
        warnings.append(
            "scan.yaml does not record the calibration source's angular profile (source_profile): "
            "assumed isotropic, the source_profile effect fits a narrower one"
        )
    try:
        return PointSource(float(diameter), AngularProfile.parse(str(text))), warnings
    except (TypeError, ValueError) as error:
        raise CalibrationError(f"the scan's calibration source: {error}") from None


def scan_gain(extra: dict[str, Any]) -> tuple[float | None, list[str]]:
    """The camera's gain (counts per electron) from ``scan.yaml``, or None to estimate it. A scan
    that says it holds no noise (``noise: none``, as an unmodified synthetic scan does) has no
    shot noise to go with that gain: its noise scale is estimated and profiled out instead."""
    gain = extra.get("counts_per_electron")
    if str(extra.get("noise", "")).strip().lower() == "none":
        return None, [
            "scan.yaml says the frames hold no noise: the noise scale is profiled out of the fit "
            "(only relative misfits count; the χ² values are against a floor of quantisation steps)"
        ]
    return (float(gain) if gain is not None else None), []


def calibrate_scan(
    scan_dir: str | Path,
    design: SystemDesign,
    *,
    fit_positions: int = 27,
    max_effects: int = 6,
    source_diameter_um: float | None = None,
    source_profile: str | None = None,
    workers: int = 1,
    progress: Progress | None = None,
) -> ScanCalibration:
    """Run the loop of the module docstring on the scan folder ``scan_dir`` taken on ``design``.

    fit_positions: positions traced for the attribution (spread over the grid).
    max_effects: effects kept at most.
    source_diameter_um: the calibration source's diameter, µm (default: the scan's
        ``source_diameter_um`` metadata, else a point).
    source_profile: the calibration source's angular profile as
        :meth:`~cm2optics.emission.source.AngularProfile.describe` writes it (default: the scan's
        ``source_profile`` metadata, else isotropic, said in the document's ``warnings``).
    workers: processes tracing the model at every position (before and after; 1: this process).
    """
    say = progress or (lambda message: None)
    scan = read_scan(scan_dir, sensor_pixel_um=design.sensor.pixel_um)
    _check_scan(scan, design)
    extra = scan.meta.extra
    source, warnings = scan_source(extra, source_diameter_um, source_profile)
    gain, noise_warning = scan_gain(extra)
    warnings += noise_warning
    for warning in warnings:
        say(f"warning: {warning}")
    simulator = TracerSimulator(design, binning=scan.meta.binning, source=source)
    files = tuple(scan.files)
    positions = scan.positions_mm
    data = ScanData(scan.images, scan.exposure_ms, positions, files, scan.meta.bit_depth)
    pitch = simulator.pitch_px()

    check_frames(data)
    subset = fit_subset(positions, fit_positions)
    with tracing_pool(workers) as pool:
        say(f"tracing the nominal design at {len(positions)} positions")
        nominal_job = submit_rates(pool, simulator, positions, {}, with_centres=True, here=subset)
        data, defect_warning = _without_defects(data, simulator, subset)
        for warning in defect_warning:
            say(f"warning: {warning}")
        warnings += defect_warning
        subset = _usable_subset(data, simulator, subset, gain)
        say(f"attributing the residual on {len(subset)} positions")
        valid = (data.counts[subset] < 2**scan.meta.bit_depth - 1) & data.good_pixels()[None]
        problem = Problem(
            simulator,
            data.counts[subset],
            scan.exposure_ms[subset],
            positions[subset],
            valid,
            library(simulator.lenslets, design.mla.pitch_mm, source.diameter_um),
            gain,
        )
        attribution = attribute(problem, max_effects=max_effects, progress=say)

        say("tracing the corrected design at every position")
        corrected_job = submit_rates(pool, simulator, positions, attribution.effects, here=subset)
        nominal, centres = nominal_job()
        before = analyse_scan(data, nominal, positions, centres, pitch, counts_per_electron=gain)
        del nominal
        _check_magnification(before)
        rate = _with_image_effects(corrected_job()[0], simulator, attribution)
    after = analyse_scan(data, rate, positions, centres, pitch, counts_per_electron=gain)
    vertices = lenslet_vertices_px(design, scan.meta.binning)
    drift, stage = flux_drift(after), stage_errors(after, simulator.pixel_um, vertices)
    exposures = frame_flux_errors(after) if drift is None else None  # a drift already reads each frame's own flux
    own_flux = drift is not None or exposures is not None
    z_scale = stage_z_scale(after, spread_rate_per_mm(design, positions[:, 2]))
    xy_map = stage_xy_map(after, vertices)
    background = background_structure(after, scan.exposure_ms)
    gain_map = sensor_gain(after, vertices, per_frame=own_flux)
    gain_warning = None if gain_map is None else describe_sensor_gain(gain_map, scan.meta.binning)
    pattern = fixed_pattern(after)
    pattern_warning = None if pattern is None else describe_fixed_pattern(pattern)
    widened = _widening_caveats(attribution, source, scan.meta.binning, after, simulator.pixel_um)
    widened += list(attribution.ambiguities)  # a larger source against crosstalk or a narrow halo, too close to call
    for warning in (drift, exposures, stage, xy_map, z_scale, gain_warning, pattern_warning, *widened):
        if warning is not None:
            say(f"warning: {warning}")
            warnings.append(warning)
    corrected = corrected_design(design, attribution)
    document = {
        "scan": str(scan_dir),
        "design": design.name,
        "design_hash": design.parameter_hash(),
        "source": source.describe(),
        "source_corrected": fitted_source(attribution.effects, source).describe(),
        "warnings": warnings,
        "sensor_defects": describe_defects(~data.good_pixels()),
        "sensor_gain": gain_map,
        "fixed_pattern": pattern,
        "corrected_design_hash": corrected.parameter_hash(),
        **_summary(before, after, attribution, problem, simulator.pixel_um, own_flux, background),
        "fit": _fit_record(subset, attribution, problem),
        "before": before.to_dict(),
        "after": after.to_dict(),
    }
    if (
        stage is not None or z_scale is not None or xy_map is not None
    ):  # the source was elsewhere: its residuals show it
        for entry in document["unexplained"]:
            found = [
                text
                for text, warning in (
                    ("frames displaced as a whole", stage),
                    ("the stage's x, y axes", xy_map),
                    ("a z scale error", z_scale),
                )
                if warning
            ]
            entry["description"] += (
                f"; the stage put the source elsewhere ({' and '.join(found)}, see warnings): part or all of this "
                "residual may be the stage's"
            )
    if gain_map is not None:  # the foci's energies follow the sensor's gain: residuals of energy show it
        for entry in document["unexplained"]:
            entry["description"] += (
                "; the foci's energies follow one smooth gain pattern over the sensor (see warnings, "
                "sensor_gain): part or all of this residual may be the sensor's"
            )
    if pattern is not None:  # offsets of whole columns or rows add to every focus over them
        for entry in document["unexplained"]:
            entry["description"] += (
                "; the dark pixels hold fixed column or row offsets (see warnings, fixed_pattern): part of this "
                "residual may be the readout's"
            )
    correction = None
    if document["unexplained"]:
        say("fitting the low-rank correction to the unexplained residual (and on held-out positions)")
        try:
            correction = fit_correction(after)
            document["correction"] = {**correction.to_dict(), "held_out": held_out_error(after)}
        except ValueError as error:  # no focus bright and whole enough
            document["warnings"].append(f"no low-rank correction: {error}")
    return ScanCalibration(document, before, after, attribution, corrected, correction)
