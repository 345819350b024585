"""A measurement of a few emitters, by tracing each one: the brute-force reference image.

Emitters come as CSV ``x_um,y_um,z_um,diameter_um,intensity`` (DESIGN.md, read with
:func:`cm2optics.formats.emitters.read_emitters`): object-space
position (µm; x, y from the central lenslet's axis, z from the nominal focal plane, +z towards
the device), bead diameter (µm; a uniform disc in the image) and relative brightness (photons
emitted, in any unit, ≥ 0). Fluorescent emitters are isotropic and emit the fluorophore's
spectrum (``gfp-emission``); each is imaged through every lenslet with the full model of
:mod:`.psf`, and the frames add up (incoherent light).

The measurement is a 16-bit TIFF of raw counts, ``counts = Σ intensity × PSF × scale + dark``
with ``scale`` chosen (unless given) so that the brightest pixel sits at ``fill`` of the
sensor's full scale, and a YAML sidecar (``NAME.yaml``) that records the scale, units, pixel
pitch and orientation. No noise is added: this image is what the 3D-LSV model must reproduce.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

import cm2optics
from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, PSFSettings, add_focus
from cm2optics.emission.source import fluorescent_bead
from cm2optics.formats.emitters import Emitters
from cm2optics.formats.measurement import write_measurement
from cm2optics.optics.sensor_effects import apply_as_built

__all__ = ["MAX_DIAMETER_UM", "TracedSource", "render_emitters", "write_traced_measurement"]

#: The largest bead the tracer renders (a uniform disc in the image), µm.
MAX_DIAMETER_UM = 200.0


def render_emitters(
    design: SystemDesign,
    emitters: Emitters,
    settings: PSFSettings | None = None,
    progress: bool = False,
) -> np.ndarray:
    """The frame of ``emitters`` (float64, (rows, cols) of the binned sensor): Σ intensity × PSF,
    in photons detected per unit of intensity; the design's as-built stray light and pixel
    crosstalk applied (its leakage needs an exposure, which this frame has not)."""
    if len(emitters) == 0:
        raise ValueError("no emitters to trace")
    if np.any(emitters.diameter_um > MAX_DIAMETER_UM):
        raise ValueError(
            f"diameter_um must lie within 0–{MAX_DIAMETER_UM:g} µm (got up to {emitters.diameter_um.max():g})"
        )
    model = EmissionModel(design, fluorescent_bead(0.0), settings=settings)
    for p in emitters.positions_um:
        model.device_point_mm(p / 1000.0)
    frame = np.zeros(model.grid.shape)
    from rich.progress import Progress

    with Progress(disable=not progress, transient=True) as bar:
        task = bar.add_task("tracing emitters", total=len(emitters))
        for position, diameter, intensity in zip(
            emitters.positions_um, emitters.diameter_um, emitters.intensity, strict=True
        ):
            if intensity > 0:
                for focus in model.foci(position / 1000.0, diameter_um=diameter):
                    add_focus(frame, focus, intensity)
            bar.advance(task)
    return apply_as_built(frame, design.as_built, model.grid.pitch_mm * 1000.0)


class TracedSource:
    """Frames traced by :func:`render_emitters` (no 3D-LSV model in the loop) presented as the
    forward model the synthesiser renders sparsely (``forward_sparse``, ``geometry``,
    ``sensor_shape``, ``n_lenslets``), so that synthetic test sets can be *traced*: the paper's
    experiments, where the mismatch between the model and the device is real.

    reference: the 3D-LSV model the test set is for — its sensor window (``provenance
    ["sensor_window"]``, [top, left, bottom, right] px of the full binned sensor) is cut out of
    each traced frame, and its geometry (chief rays, pixels per voxel) is the one the views and
    reconstructions use; binning: the sensor binning of the reference model. Units: photons per
    unit intensity (the synthesiser scales each clean frame to a peak of 1)."""

    def __init__(self, design: SystemDesign, reference: Any, binning: int):
        self.design = design
        self.settings = PSFSettings(binning=binning)
        self.geometry = reference.geometry
        self.sensor_shape = tuple(int(v) for v in reference.sensor_shape)
        self.n_lenslets = int(reference.n_lenslets)
        window = getattr(reference, "provenance", {}).get("sensor_window") or [0, 0, *self.sensor_shape]
        self.window = tuple(int(v) for v in window)
        self.provenance = {"traced": design.name, "binning": int(binning), "sensor_window": list(self.window)}

    def forward_sparse(self, emitters: Emitters, per_lenslet: bool = False) -> np.ndarray:
        """The traced frame of ``emitters`` on the reference's sensor window, (rows, cols) float64."""
        if per_lenslet:
            raise ValueError(
                "a traced frame has no per-lenslet images (demixed views): make the test set with view_px = 0"
            )
        if len(emitters) == 0:
            return np.zeros(self.sensor_shape)
        frame = render_emitters(self.design, emitters, self.settings)
        top, left, bottom, right = self.window
        if frame.shape[0] < bottom or frame.shape[1] < right:
            raise ValueError(
                f"the traced {frame.shape[0]} × {frame.shape[1]}-px frame (binning {self.settings.binning}) does not hold "
                f"the reference model's sensor window {list(self.window)}: is the binning the model's?"
            )
        return frame[top:bottom, left:right]


def write_traced_measurement(
    path: str | Path,
    frame: np.ndarray,
    design: SystemDesign,
    binning: int,
    *,
    fill: float = 0.8,
    scale: float | None = None,
    dark_level: float = 0.0,
    extra: dict[str, Any] | None = None,
) -> tuple[Path, Path]:
    """Write ``frame`` (photons detected per unit intensity) as a 16-bit TIFF of counts at the
    sensor's bit depth and its YAML sidecar; returns both paths. ``scale`` (counts per unit of
    frame) defaults to putting the brightest pixel at ``fill`` (0.05–1) of full scale."""
    if not (math.isfinite(fill) and 0.05 <= fill <= 1.0):
        raise ValueError(f"fill = {fill!r}: must lie within 0.05–1")
    bits = design.sensor.bit_depth
    full = 2**bits - 1
    if not (math.isfinite(dark_level) and 0 <= dark_level < full):
        raise ValueError(f"dark_level = {dark_level!r}: must lie within 0–{full} counts")
    peak = float(frame.max())
    if scale is None:
        scale = (fill * full - dark_level) / peak if peak > 0 else 1.0
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale = {scale!r}: must be a finite number > 0")
    counts = np.clip(np.rint(frame * scale + dark_level), 0, full).astype(np.uint16)
    sidecar = {
        "pixel_um": design.sensor.pixel_um * binning,
        "binning": binning,
        "bit_depth": bits,
        "dark_level": dark_level,
        "counts_per_unit": float(scale),
        "noise": None,
        "units": "counts = sum(intensity x photons detected per photon emitted) x counts_per_unit + dark_level",
        "image_orientation": "sensor frame: column along +x, row along +y of the device frame, optical axis at the centre",
        "synthetic": True,
        "design": design.name,
        "design_hash": design.parameter_hash(),
        "generator": f"cm2optics {cm2optics.__version__} (cm2optics.emission.image)",
        **(extra or {}),
    }
    return write_measurement(path, counts, sidecar)
