"""Full-field reconstruction with trained CM²Net weights: one pass, no tiles.

1. check the measurement (2-D, real numbers, finite, the model's sensor shape);
2. optionally bring it to the training statistics: ``max`` (divide by its maximum) or
   ``histogram`` (match its histogram to the training views' quantiles stored with the weights —
   the paper's preprocessing of measured frames);
3. crop the nine views at the chief rays of the model's geometry (zeros beyond the sensor, as in
   training), ``view_px`` on a side (default: the training views'), registered onto the model's
   geometry if the weights were trained so (:mod:`~cm2optics.recon.net.register`);
4. run the network on the whole view stack (fully convolutional, batch norms folded into the
   convolutions, channels-last memory layout), σ → [0, 1];
5. resample the output from the views' orientation into the volume's (the image through a
   lenslet is inverted) on a grid centred on the axis whose lateral voxel is the model's
   object-side pixel (the config's voxel within 2 %) and axial voxel the config's, each plane
   moved by the weights' lateral correction (:mod:`~cm2optics.recon.net.lateral`: the
   depth-dependent magnification a convolutional network cannot learn), and detect emitters
   (:func:`cm2optics.metrics.detect_emitters`).

Border: nothing is cropped. The outer ``border_px`` (the largest refocusing shift) of the field
is where the shift-and-add lacked light from beyond the views; at full field that is outside the
illuminated disc, and the result says how wide it is.

The model must be the one the weights were trained for: the same lenslet count, the same integer
refocusing shifts recomputed from its geometry, one view pixel per voxel; anything else raises
:class:`~.weights.GeometryMismatchError`.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.volume import VolumeGrid
from cm2optics.recon.net.data import pixel_voxel_um
from cm2optics.recon.net.lateral import LateralCorrection, volume_on_grid
from cm2optics.recon.net.model import fused_for_inference
from cm2optics.recon.net.refocus import refocus_planes
from cm2optics.recon.net.weights import GeometryMismatchError, LoadedNet, NetInputError, load_weights

__all__ = [
    "NetResult",
    "PREPROCESS",
    "histogram_match",
    "reconstruct_net_file",
    "reconstruct_with_net",
    "views_from_measurement",
]

PREPROCESS = ("none", "max", "histogram")


@dataclass(frozen=True)
class NetResult:
    """volume: (z, y, x) float32 in [0, 1] on ``grid`` (voxel size in ``grid.voxel_um``);
    emitters: detections at ``threshold``; demixed: (J, V, V) the demixed views; border_px: the
    field margin the refocusing could not fill; seconds: timings."""

    volume: np.ndarray
    grid: VolumeGrid
    emitters: Emitters
    threshold: float
    demixed: np.ndarray
    border_px: int
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def voxel_um(self) -> tuple[float, float, float]:
        return self.grid.voxel_um


def histogram_match(image: np.ndarray, reference_quantiles: np.ndarray) -> np.ndarray:
    """``image`` mapped so that its quantiles become ``reference_quantiles`` (levels evenly
    spaced over 0…1), piecewise linearly; float32."""
    ref = np.asarray(reference_quantiles, float)
    if ref.ndim != 1 or len(ref) < 2 or not np.all(np.isfinite(ref)):
        raise ValueError("reference_quantiles must be a 1-D array of ≥ 2 finite values")
    levels = np.linspace(0.0, 1.0, len(ref))
    image = np.asarray(image, float)
    q = np.quantile(image, levels)
    q = q + np.arange(len(q)) * 1e-12 * max(float(np.ptp(q)), 1.0)  # strictly increasing
    return np.interp(image, q, np.maximum.accumulate(ref)).astype(np.float32)


def _chief_rays(model: Any) -> np.ndarray:
    if hasattr(model, "geometry") and hasattr(model.geometry, "focus"):
        return np.asarray(model.geometry.focus(0.0, 0.0, 0.0), float).reshape(-1, 2)
    if hasattr(model, "chief_rays_px"):
        return np.asarray(model.chief_rays_px(), float).reshape(-1, 2)
    raise GeometryMismatchError(
        f"{type(model).__name__}: has no chief rays (need a 3D-LSV model or an operator with chief_rays_px)"
    )


def views_from_measurement(measurement: np.ndarray, model: Any, view_px: int) -> np.ndarray:
    """(J, view_px, view_px) views of ``measurement`` cropped at ``model``'s chief rays."""
    from cm2optics.synth.views import crop_views

    return crop_views(np.asarray(measurement, np.float32), _chief_rays(model), view_px)


def field_view_px(field_mm: float, voxel_um: float, border_px: int) -> int:
    """Side (px, even) of the views that hold a disc of ``field_mm`` at one view pixel per
    ``voxel_um`` (within the 2 % :func:`check_geometry` allows) and the refocusing border
    (``border_px``, the largest shift) on each side: 1,732 for the 7-mm field at 4.15 µm and 5 px."""
    side = math.ceil(field_mm * 1000.0 / voxel_um - 1e-9) * 1.02 + 2 * border_px
    return 2 * math.ceil(side / 2)


def _load_model(model: Any, grid: VolumeGrid, config: Any) -> Any:
    if model is None:
        from cm2optics.recon.net.data import inference_model

        return inference_model(config)
    if isinstance(model, str | Path):
        from cm2optics.synth.imaging import load_imaging

        return load_imaging(model, grid).source
    return getattr(model, "source", model)  # an Imaging → its model


def _check_measurement(measurement: Any, shape: tuple[int, int], name: str) -> np.ndarray:
    array = np.asarray(measurement)
    if array.dtype.kind not in "uif":
        raise NetInputError(f"{name}: dtype {array.dtype} is not a real number type (need an integer or float image)")
    if array.ndim != 2:
        raise NetInputError(f"{name}: shape {array.shape} is not one image (y, x)")
    if tuple(array.shape) != tuple(shape):
        raise NetInputError(f"{name}: shape {array.shape} is not the model's sensor {tuple(shape)} (binning?)")
    array = array.astype(np.float32)
    if not np.all(np.isfinite(array)):
        raise NetInputError(f"{name}: contains NaN or infinite values")
    return array


def check_geometry(loaded: LoadedNet, model: Any) -> tuple[np.ndarray, Any]:
    """Refuse a model whose geometry differs from the weights'; returns (pixels per voxel, model)."""
    from cm2optics.synth.imaging import Imaging

    config = loaded.config
    grid = config.synth.grid
    planes = loaded.planes
    J = int(planes.shifts_px.shape[1])
    n_lenslets = int(getattr(model, "n_lenslets", len(_chief_rays(model))))
    where = f"{loaded.folder}"
    if n_lenslets != J:
        raise GeometryMismatchError(f"{where}: trained for {J} lenslets, the model has {n_lenslets}")
    z = planes.z_mm
    try:
        mine = refocus_planes(model, (float(grid.axis_mm(0)[0]), float(grid.axis_mm(0)[-1])), config.refocus_planes)
    except ValueError as error:
        raise GeometryMismatchError(f"{where}: the model's geometry gives no refocusing planes ({error})") from None
    if mine.n_planes != planes.n_planes or not np.array_equal(mine.shifts_px, planes.shifts_px):
        diff = (
            np.abs(mine.shifts_px - planes.shifts_px).max() if mine.shifts_px.shape == planes.shifts_px.shape else None
        )
        raise GeometryMismatchError(
            f"{where}: the model's refocusing ({mine.n_planes} planes"
            + (f", shifts up to {diff} px apart" if diff is not None else "")
            + f") is not the one the weights learned ({planes.n_planes} planes at {z.min() * 1000:.0f}…{z.max() * 1000:.0f} µm)"
        )
    try:
        scale = Imaging(model, grid).pixels_per_voxel()
    except ValueError as error:
        raise GeometryMismatchError(f"{where}: {error}") from None
    if scale is None or np.any(np.abs(np.abs(scale) - 1.0) > 0.02):
        raise GeometryMismatchError(
            f"{where}: one view pixel must image one {grid.voxel_um[1]:g}-µm voxel; this model maps {scale} pixels per voxel"
        )
    return np.asarray(scale, float), model


def reconstruct_with_net(
    measurement: np.ndarray,
    weights: str | Path | LoadedNet,
    model: Any,
    *,
    preprocess: str = "none",
    threshold: float | None = None,
    view_px: int | None = None,
    device: str = "cpu",
    name: str = "measurement",
    lateral: LateralCorrection | None = None,
    grid: VolumeGrid | None = None,
    registration: np.ndarray | None = None,
) -> NetResult:
    """The volume of one measurement (see the module docstring).

    measurement: (H, W) sensor frame (integers or floats; a synthetic one is already normalised).
    weights: a weights folder (or :func:`load_weights`' result). model: the forward model (a
    3D-LSV model or its file, or an operator with chief rays; None: the one the weights were
    trained through, on its whole sensor). preprocess: ``none``, ``max`` or
    ``histogram``. threshold: detection threshold on [0, 1] (default: the weights' operating
    threshold, chosen on validation volumes, else the config's).
    view_px: side of the views (default: the training views'). name: how errors call the input.
    lateral: the output planes' lateral correction (default: the one stored with the weights,
    none if they carry none; :mod:`~cm2optics.recon.net.lateral`). grid: the output grid, centred
    on the axis (default: the views' size at the model's object-side pixel; its planes must be the
    network's), e.g. a test set's, onto which the planes are resampled. registration: (J, 2, V, V)
    sampling positions that register the views onto the model's geometry
    (:func:`~cm2optics.recon.net.register.registration_map`; None: the model's own if the weights
    were trained on registered views, else the views as cropped)."""
    t0 = time.perf_counter()
    if preprocess not in PREPROCESS:
        raise ValueError(f"preprocess = {preprocess!r}: must be one of {', '.join(PREPROCESS)}")
    loaded = weights if isinstance(weights, LoadedNet) else load_weights(weights, device=device)
    config = loaded.config
    model = _load_model(model, config.synth.grid, config)
    scale, model = check_geometry(loaded, model)
    image = _check_measurement(measurement, tuple(int(v) for v in model.sensor_shape), name)
    if preprocess == "max":
        image = image / max(float(image.max()), 1e-12)
    elif preprocess == "histogram":
        if loaded.histogram is None:
            raise NetInputError(
                f"{loaded.folder}: these weights carry no reference histogram; use preprocess 'max' or 'none'"
            )
        image = histogram_match(image, loaded.histogram)
    V = int(view_px or config.synth.view_px)
    views = views_from_measurement(image, model, V)
    if registration is None and config.register_views:
        from cm2optics.recon.net.register import registration_map

        try:
            registration = registration_map(model, V)
        except ValueError as error:
            raise GeometryMismatchError(f"{loaded.folder}: trained on registered views; {error}") from None
    if registration is not None:
        from cm2optics.recon.net.register import register_views

        views = register_views(views, registration)
    t1 = time.perf_counter()
    # channels-last: 0.58× the time of the default layout at full field on this CPU; batch norms
    # folded into the convolutions: fewer passes over the feature maps (BENCHMARKS.md)
    net = fused_for_inference(loaded.net).to(device, memory_format=torch.channels_last)
    with torch.inference_mode():
        x = torch.from_numpy(views)[None].to(device).contiguous(memory_format=torch.channels_last)
        demix_logits, volume_logits = net(x)
        volume = torch.sigmoid(volume_logits)[0].float().cpu().numpy()
        demixed = torch.sigmoid(demix_logits)[0].float().cpu().numpy() if demix_logits is not None else views
    t2 = time.perf_counter()
    own = VolumeGrid((volume.shape[0], V, V), pixel_voxel_um(config, scale))
    if grid is None:
        grid = own
    elif grid.shape[0] != own.shape[0] or not np.isclose(grid.voxel_um[0], own.voxel_um[0], rtol=1e-6):
        raise ValueError(
            f"grid {grid.shape} of {grid.voxel_um} µm: the network's planes are {own.shape[0]} at {own.voxel_um[0]} µm"
        )
    if lateral is None:
        lateral = loaded.lateral or LateralCorrection()
    z_mm = loaded.net.volume_z_mm.cpu().numpy()
    volume = volume_on_grid(
        volume, z_mm, own.voxel_um[1:], scale, lateral, out_shape=grid.shape[1:], out_voxel_um=grid.voxel_um[1:]
    )
    from cm2optics.metrics import detect_emitters

    threshold = loaded.threshold if threshold is None else float(threshold)
    emitters = detect_emitters(volume, grid, threshold)
    t3 = time.perf_counter()
    return NetResult(
        volume,
        grid,
        emitters,
        threshold,
        demixed,
        loaded.planes.max_shift_px,
        {"prepare": t1 - t0, "network": t2 - t1, "detect": t3 - t2, "total": t3 - t0},
    )


def reconstruct_net_file(
    measurement_path: str | Path,
    weights: str | Path,
    out_path: str | Path,
    *,
    model: str | Path | None = None,
    emitters_out: str | Path | None = None,
    preprocess: str = "histogram",
    threshold: float | None = None,
    dark_level: float = 0.0,
    field_mm: float | None = None,
) -> dict[str, Any]:
    """Read a measurement, reconstruct it with the weights folder ``weights``, write the volume
    (TIFF with ImageJ spacing, or .npy), ``<out>.json`` beside it and, if asked, the detected
    emitters (CSV, µm, centred on the axis); returns the JSON record. field_mm: reconstruct a disc
    of this diameter (views that hold it, :func:`field_view_px`; e.g. 7 for the whole field of a
    full-sensor frame) instead of the training views' field."""
    from cm2optics.errors import UserError
    from cm2optics.formats.atomic import write_json_atomic
    from cm2optics.formats.emitters import write_emitters
    from cm2optics.formats.measurement import read_measurement
    from cm2optics.formats.volume import write_volume

    out_path = Path(out_path)
    if out_path.suffix.lower() not in (".tif", ".tiff", ".npy"):
        raise UserError(f"--out {out_path}: give a .tif or .npy file name")
    if emitters_out is not None and Path(emitters_out).suffix.lower() != ".csv":
        raise UserError(f"--emitters-out {emitters_out}: give a .csv file name")
    measurement = read_measurement(measurement_path, dark_level)
    loaded = load_weights(weights)
    view_px = None
    if field_mm is not None:
        view_px = field_view_px(field_mm, loaded.config.synth.voxel_um[1], loaded.planes.max_shift_px)
    result = reconstruct_with_net(
        measurement,
        loaded,
        model,
        preprocess=preprocess,
        threshold=threshold,
        view_px=view_px,
        name=str(measurement_path),
    )
    write_volume(out_path, result.volume, result.grid.voxel_um)
    record: dict[str, Any] = {
        "method": "net",
        "measurement": str(measurement_path),
        "weights": str(weights),
        "model": str(model) if model is not None else loaded.config.forward_model,
        "volume": str(out_path),
        "shape": list(result.volume.shape),
        "voxel_um": list(result.grid.voxel_um),
        "preprocess": preprocess,
        "threshold": result.threshold,
        "n_emitters": len(result.emitters),
        "view_px": view_px or loaded.config.synth.view_px,
        "border_px": result.border_px,
        "lateral_correction": json.loads(loaded.lateral.to_json()) if loaded.lateral is not None else None,
        "seconds": {k: round(v, 3) for k, v in result.seconds.items()},
    }
    if emitters_out is not None:
        write_emitters(emitters_out, result.emitters)
        record["emitters"] = str(emitters_out)
    write_json_atomic(out_path.with_suffix(".json"), record)
    return record
