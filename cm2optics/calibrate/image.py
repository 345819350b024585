"""Calibrate a design against a measured frame of beads whose positions are known, and show what
the correction does to the reconstruction: ``cm2 calibrate image``.

A frame with known sources is a measurement like a scan image: the model's frame is the sum of
the known emitters' images (each scaled by its CSV intensity), so the scan loop's machinery
applies unchanged — the attribution (:mod:`.attribute`) fits every library effect to the frame
(:class:`FrameSimulator`: one image holding the foci of all emitters), and the residual analysis
(:mod:`.residual`) measures the foci of each emitter in turn (the frame once per emitter, with
that emitter's foci as the windows), so that per-focus numbers and the unexplained residual's
signature keep their lenslets and field positions. A previous ``cm2 calibrate scan`` report may
give the effects instead (``--scan-report``).

The frame is then reconstructed twice by FISTA with 3D-LSV models built from the same
simulator's single-source images on a small grid of nodes around the beads (:func:`lsv_model`):
the nominal model, and the corrected one (the effects, and the frame offset the registration
found: where the sensor sits, which the beads' coordinates fix). Each volume is scored against the reference emitters
at its own F1-optimal threshold (``cm2 evaluate``'s default), so recall, precision, F1 and the
localisation RMSE before and after compare the models, not the thresholds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.calibrate.attribute import Attribution, Problem, attribute
from cm2optics.calibrate.effects import apply_image_effects, library
from cm2optics.calibrate.residual import CalibrationError, ResidualAnalysis, ScanData, analyse_scan
from cm2optics.calibrate.scan import corrected_design, effects_document
from cm2optics.calibrate.simulate import Simulator, Values
from cm2optics.calibrate.unexplained import describe_unexplained
from cm2optics.design import SystemDesign
from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid

__all__ = [
    "BeadsFrame",
    "FrameSimulator",
    "FittedEffects",
    "ImageCalibration",
    "calibrate_image",
    "check_frame",
    "frame_binning",
    "scan_report_effects",
]

Progress = Callable[[str], None]
#: LSV nodes along x and y around the beads, and along z.
LATERAL_NODES, DEPTH_NODES = 5, 3


@dataclass(frozen=True)
class BeadsFrame:
    """A measured frame: raw counts (y, x), the reference emitters, the exposure (ms), ADC bits, and
    the camera's gain (counts per photo-electron; None: estimated from the frame, which a model
    far from the data inflates)."""

    counts: np.ndarray
    emitters: Emitters
    exposure_ms: float = 1.0
    bit_depth: int = 16
    name: str = "frame"
    counts_per_electron: float | None = None


def frame_binning(shape: tuple[int, ...], design: SystemDesign) -> int:
    """The binning (1–16) at which ``design``'s sensor gives a frame of ``shape`` (y, x); a clear
    error when none does."""
    sensor = design.sensor
    for binning in range(1, 17):
        if (sensor.height_px // binning, sensor.width_px // binning) == tuple(shape):
            return binning
    raise CalibrationError(
        f"wrong sensor size: the frame is {shape[0]} × {shape[1]} px; the design's sensor ({sensor.name}, "
        f"{sensor.height_px} × {sensor.width_px} px) binned 1–16× never gives that"
    )


def check_frame(frame: BeadsFrame, design: SystemDesign) -> None:
    """Clear errors for a frame that cannot be compared: not 2-D, NaN or infinite pixels, no
    emitters, emitters outside the design's field (its diameter ``volume.field_mm``) or depth."""
    if frame.counts.ndim != 2:
        raise CalibrationError(f"the frame must be one image (y, x); got shape {frame.counts.shape}")
    if not np.all(np.isfinite(frame.counts)):
        raise CalibrationError(f"{frame.name}: the frame holds NaN or infinite pixels")
    emitters = frame.emitters
    if len(emitters) == 0:
        raise CalibrationError("the emitter list is empty: calibrating against a frame needs its reference beads")
    if not np.any(emitters.intensity > 0):
        raise CalibrationError("every emitter has intensity 0: the model would be a dark frame")
    half_field_um = design.volume.field_mm * 500.0
    radius = np.hypot(emitters.x_um, emitters.y_um)
    half_depth_um = design.volume.depth_mm * 500.0
    outside = np.flatnonzero((radius > half_field_um) | (np.abs(emitters.z_um) > half_depth_um))
    if len(outside):
        i = int(outside[0])
        raise CalibrationError(
            f"{len(outside)} emitter(s) outside the design's field (radius {half_field_um / 1000:g} mm, depth "
            f"±{half_depth_um / 1000:g} mm), the first at row {i + 1}: ({emitters.x_um[i]:g}, {emitters.y_um[i]:g}, "
            f"{emitters.z_um[i]:g}) µm"
        )


@dataclass
class FrameSimulator:
    """A :class:`~cm2optics.calibrate.simulate.Simulator` whose one image is a frame of known
    emitters: ``rates`` of the emitters' positions (K, 3) mm returns (1, y, x), the sum of the
    base simulator's images weighted by ``weights`` (K,); ``focus_centres_px`` returns
    (1, K·J, 2), every emitter's foci. Effects and their costs are the base simulator's."""

    base: Simulator
    weights: np.ndarray
    trace_at: Callable[[Values], None] | None = field(default=None, init=False)

    def __post_init__(self) -> None:
        self.weights = np.asarray(self.weights, np.float32)
        self.trace_at = getattr(self.base, "trace_at", None)  # None: the simulator never re-traces

    @property
    def lenslets(self) -> int:
        return self.base.lenslets

    @property
    def pixel_um(self) -> float:
        return self.base.pixel_um

    @property
    def shape(self) -> tuple[int, int]:
        return self.base.shape

    @property
    def anchor(self) -> Values:
        return getattr(self.base, "anchor", {})

    @property
    def retraced(self) -> frozenset[str]:
        return frozenset(getattr(self.base, "retraced", ()))

    def supports(self, effect: Any) -> bool:
        return self.base.supports(effect)

    def pitch_px(self) -> float:
        return self.base.pitch_px()

    def rates(
        self, positions_mm: np.ndarray, values: Values, offset_px: tuple[float, float] = (0.0, 0.0)
    ) -> np.ndarray:
        images = self.base.rates(positions_mm, values, offset_px)
        return np.tensordot(self.weights, images, axes=1)[None].astype(np.float32)

    def focus_centres_px(self, positions_mm: np.ndarray) -> np.ndarray:
        return self.base.focus_centres_px(positions_mm).reshape(1, -1, 2)


@dataclass(frozen=True)
class ImageCalibration:
    """The result: the JSON document, the residual analyses, the corrected design, the volumes."""

    document: dict[str, Any]
    before: ResidualAnalysis
    after: ResidualAnalysis
    corrected_design: SystemDesign
    volumes: dict[str, np.ndarray]
    evaluations: dict[str, Any]
    grid: VolumeGrid


def _weights(emitters: Emitters) -> np.ndarray:
    """(K,) emitter intensities relative to their mean (the flux scale is fitted)."""
    return emitters.intensity / float(np.mean(emitters.intensity))


def model_frame(simulator: Simulator, frame: BeadsFrame, values: Values) -> np.ndarray:
    """(y, x) the model's frame, counts per ms of unit flux: the emitters' images with ``values``
    (optical effects by the simulator, sensor-side ones applied, leakage left to the registration)."""
    rate = FrameSimulator(simulator, _weights(frame.emitters)).rates(frame.emitters.positions_mm(), values)
    return apply_image_effects(rate, values, simulator.pixel_um)[0]


def _analyse(simulator: Simulator, frame: BeadsFrame, rate: np.ndarray) -> ResidualAnalysis:
    """The residual of the frame against the model frame ``rate``, the foci of emitter k measured
    in the k-th copy of the frame (read-only views, no copies in memory)."""
    k = len(frame.emitters)
    positions = frame.emitters.positions_mm()
    data = ScanData(
        np.broadcast_to(frame.counts, (k,) + frame.counts.shape),
        np.full(k, frame.exposure_ms),
        positions,
        tuple(f"{frame.name} · emitter {i + 1}" for i in range(k)),
        frame.bit_depth,
    )
    model = np.broadcast_to(rate, (k,) + rate.shape)
    centres = simulator.focus_centres_px(positions)
    return analyse_scan(
        data, model, positions, centres, simulator.pitch_px(), counts_per_electron=frame.counts_per_electron
    )


def _declared_diameter_um(simulator: Simulator) -> float:
    """The beads' diameter the simulator images (µm; the traced source's, else a point)."""
    source = getattr(simulator, "source", None)
    return float(source.diameter_um) if source is not None else 0.0


def _attribute(simulator: Simulator, frame: BeadsFrame, max_effects: int, say: Progress) -> Attribution:
    """The library effects the frame's residual asks for (the scan loop's attribution on one image)."""
    counts = frame.counts[None].astype(np.float32)
    problem = Problem(
        FrameSimulator(simulator, _weights(frame.emitters)),
        counts,
        np.array([frame.exposure_ms]),
        frame.emitters.positions_mm(),
        counts < 2**frame.bit_depth - 1,
        library(simulator.lenslets, source_diameter_um=_declared_diameter_um(simulator)),
        frame.counts_per_electron,
        flat_field=False,  # one frame of unknown emitters: a gain pattern is not told from their brightness
    )
    return attribute(problem, max_effects=max_effects, progress=say)


def scan_report_effects(folder: str | Path) -> Values:
    """The fitted effects of a ``cm2 calibrate scan`` report (its ``calibration.json``), as the
    simulators take them (a per-lenslet effect keyed ``name[lenslet]``)."""
    import json

    path = Path(folder) / "calibration.json"
    if not path.is_file():
        raise CalibrationError(f"{folder}: no calibration.json (give the --out folder of `cm2 calibrate scan`)")
    try:
        effects = json.loads(path.read_text())["effects"]
        values = {}
        for effect in effects:
            parameters = {k: float(v) for k, v in effect["parameters"].items() if k != "lenslet"}
            lenslet = effect["parameters"].get("lenslet")
            values[effect["name"] if lenslet is None else f"{effect['name']}[{int(lenslet)}]"] = parameters
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        raise CalibrationError(f"{path}: not a calibration report ({error})") from None
    return values


def reconstruction_grid(frame: BeadsFrame, design: SystemDesign, binning: int) -> VolumeGrid:
    """A grid centred on the axis just covering the beads (two voxels' margin): lateral voxels of
    one image pixel in the object (pixel / magnification), axial ones of ``volume.axial_step_um``."""
    from cm2optics.optics import first_order

    lateral = design.sensor.pixel_um * binning / first_order.magnification(design)
    axial = design.volume.axial_step_um
    e = frame.emitters
    half_xy = float(np.max(np.abs(np.concatenate([e.x_um, e.y_um])))) + 2 * lateral
    nxy = 2 * math.ceil(half_xy / lateral) + 1
    nz = 2 * math.ceil(float(np.max(np.abs(e.z_um))) / axial) + 1
    return VolumeGrid((nz, nxy, nxy), (axial, lateral, lateral))


def lsv_model(
    simulator: Simulator,
    design: SystemDesign,
    binning: int,
    values: Values,
    grid: VolumeGrid,
    rank: int,
    offset_px: tuple[float, float] = (0.0, 0.0),
):
    """A 3D-LSV model (:class:`~cm2optics.lsv.model.LSVModel`) of ``simulator`` with ``values`` and
    the sensor displaced by ``offset_px`` (row, col): its single-source images on
    LATERAL_NODES² × DEPTH_NODES nodes spanning ``grid``, cut around the design's paraxial chief
    rays (Keys-interpolated windows), decomposed to ``rank``."""
    from cm2optics.lsv.build import default_patch_px, model_from_crops
    from cm2optics.lsv.kernels import sample_window
    from cm2optics.lsv.toy import AnalyticCM2, analytic_geometry

    half = np.array(grid.extent_um) / 2000.0  # (z, y, x) mm
    xs = np.linspace(-half[2], half[2], LATERAL_NODES)
    ys = np.linspace(-half[1], half[1], LATERAL_NODES)
    zs = np.linspace(-half[0], half[0], DEPTH_NODES) if half[0] > 0 else np.linspace(-0.05, 0.05, DEPTH_NODES)
    geometry = analytic_geometry(AnalyticCM2.from_design(design, binning=binning), zs)
    positions = np.array([[x, y, z] for z in zs for y in ys for x in xs])
    index = np.array([[i, j, k] for k in range(len(zs)) for j in range(len(ys)) for i in range(len(xs))])
    images = apply_image_effects(simulator.rates(positions, values, offset_px), values, simulator.pixel_um)
    patch = (default_patch_px(binning),) * 2
    crops = np.stack(
        [
            np.stack([sample_window(image, centre, patch) for centre in geometry.focus(*position)])
            for image, position in zip(images, positions, strict=True)
        ]
    ).astype(np.float32)
    model, _ = model_from_crops(
        crops,
        index,
        (xs, ys, zs),
        geometry,
        rank=min(rank, len(positions)),
        sensor_shape=simulator.shape,
        pixel_um=simulator.pixel_um,
        axial_um=grid.voxel_um[0],
        provenance={"source": "cm2 calibrate image: the calibration simulator's single-source images"},
    )
    return model


def _scores(evaluation: Any) -> dict[str, Any]:
    m = evaluation.metrics
    return {k: m[k] for k in ("recall", "precision", "f1", "n_tp", "n_fp", "n_fn", "rmse_lateral_um", "rmse_axial_um")}


def reconstruct_and_score(
    frame: BeadsFrame, dark_level: float, model: Any, grid: VolumeGrid, options: Any
) -> tuple[np.ndarray, Any]:
    """FISTA of the frame (less ``dark_level``) with ``model``'s operator on ``grid``, scored
    against the reference emitters at the volume's F1-optimal threshold."""
    from cm2optics.metrics import evaluate_volume, f1_optimal_threshold
    from cm2optics.recon.reconstruct import reconstruct

    signal = frame.counts.astype(np.float32) - np.float32(dark_level)
    volume, _ = reconstruct(signal, model.operator(grid), options)
    threshold, _ = f1_optimal_threshold([(volume, grid, frame.emitters)])
    return volume, evaluate_volume(volume, grid, frame.emitters, threshold)


def calibrate_image(
    frame: BeadsFrame,
    design: SystemDesign,
    simulator: Simulator,
    *,
    binning: int,
    effects: Values | None = None,
    max_effects: int = 6,
    rank: int = 8,
    recon_options: Any = None,
    progress: Progress | None = None,
) -> ImageCalibration:
    """Calibrate ``design`` (simulated by ``simulator`` at ``binning``) against ``frame``: the
    effects named by the attribution (or ``effects``, e.g. from a scan report), the residual
    before and after, and the reconstruction's scores with the nominal and the corrected model."""
    from cm2optics.recon.reconstruct import ReconOptions

    say = progress or (lambda message: None)
    check_frame(frame, design)
    options = recon_options or ReconOptions(max_iter=60)
    if effects is None:
        say(f"attributing the frame's residual ({len(frame.emitters)} emitters)")
        attribution = _attribute(simulator, frame, max_effects, say)
        effects = attribution.effects
    else:
        attribution = FittedEffects(effects)
    say("comparing the frame with the nominal and the corrected model")
    before = _analyse(simulator, frame, model_frame(simulator, frame, {}))
    after = _analyse(simulator, frame, model_frame(simulator, frame, effects))
    grid = reconstruction_grid(frame, design, binning)
    volumes, evaluations = {}, {}
    offset = tuple(float(v) for v in after.registration.offset_px)
    for label, values, shift in (("before", {}, (0.0, 0.0)), ("after", effects, offset)):
        say(f"building the {'nominal' if label == 'before' else 'corrected'} LSV model and reconstructing")
        model = lsv_model(simulator, design, binning, values, grid, rank, shift)
        volumes[label], evaluations[label] = reconstruct_and_score(
            frame, before.registration.dark_level, model, grid, options
        )
    scores = {label: _scores(evaluations[label]) for label in ("before", "after")}
    corrected = corrected_design(design, attribution)
    document = {
        "frame": frame.name,
        "design": design.name,
        "design_hash": design.parameter_hash(),
        "corrected_design_hash": corrected.parameter_hash(),
        "emitters": len(frame.emitters),
        "binning": binning,
        "effects": effects_document(attribution),
        "effects_from": "attribution" if effects is attribution.effects else "scan report",
        "nmse_before": round(before.nmse_total, 6),
        "nmse_after": round(after.nmse_total, 6),
        "chi2_before": round(before.chi2_total, 4),
        "chi2_after": round(after.chi2_total, 4),
        "unexplained": describe_unexplained(after, simulator.pixel_um),
        **{f"{k}_{label}": v for label in ("before", "after") for k, v in scores[label].items()},
        "frame_offset_px": [round(v, 3) for v in offset],
        "reconstruction": {"method": options.method, "max_iter": options.max_iter, "l1": options.l1, "rank": rank},
        "grid": grid.to_dict(),
    }
    return ImageCalibration(document, before, after, corrected, volumes, evaluations, grid)


@dataclass(frozen=True)
class FittedEffects:
    """Effects fitted elsewhere (a scan report): what the report's helpers read of an attribution."""

    effects: Values
    uncertainties: Values = field(default_factory=dict)
