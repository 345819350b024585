"""The emission tracer as a calibration simulator: effects become the design's ``as_built`` values.

:class:`TracerSimulator` implements :class:`~cm2optics.calibrate.simulate.Simulator` by tracing
the design (:class:`cm2optics.emission.psf.EmissionModel`, one position at a time as
:func:`cm2optics.emission.scan.simulate_position` does) with the effect values written into
the design, so that a fitted effect is a design value every stage honours:

==========================  ============================================================
effect (parameters)         design field
==========================  ============================================================
mla_decenter (dx, dy mm)    ``as_built.mla_decenter_x_mm``, ``as_built.mla_decenter_y_mm``
mla_rotation (angle_deg)    ``as_built.mla_rotation_deg``
mla_spacing (delta_mm)      ``imaging.mla_to_sensor_mm`` + delta
mla_tilt (tilt_x/y_deg)     ``as_built.mla_tilt_x_deg``, ``as_built.mla_tilt_y_deg``
sensor_tilt (tilt_x/y_deg)  ``as_built.sensor_tilt_x_deg``, ``as_built.sensor_tilt_y_deg``
partial_lenslets[side]      ``mla.partial_sides`` + side, ``mla.partial_border_mm`` = border
                            (the design holds one border for every side: the widest found)
lenslet_pitch (delta_mm)    ``as_built.lenslet_pitch_delta_mm``
lenslet_decenter[j]         ``as_built.lenslet_decenter_mm[j]``
lenslet_transmission[j]     ``as_built.lenslet_transmission[j]``
vignetting                  ``as_built.vignetting_radius_delta_mm``
source_profile              the calibration source's Gaussian profile (not the device's:
                            falloff f → 1/e² half-angle 1/√f rad, at most 180°; 0: isotropic)
source_size (diameter_um)   the calibration source's diameter (not the device's: ``cm2 psf
                            simulate --pinhole-um``, scan.yaml ``source_diameter_um``)
frame offset (row, col px)  ``as_built.sensor_offset_*_um`` = −offset × the binned pitch
==========================  ============================================================

The sensor-side effects (stray light, crosstalk, leakage) are supported, and, as for every
simulator, applied on top of these images by :mod:`.effects` (their design fields are
``as_built.stray_light_*``, ``pixel_crosstalk_fraction``, ``leakage_counts_per_ms``).

Positions are object space of the *nominal* design (x, y from the central lenslet's nominal
axis, z from its nominal focal plane, +z towards the device, mm), so that a design whose MLA
sits higher images the same physical source positions: they are converted to the changed
design's object space through the device frame.

Images are in counts per ms of a unit source, as ``PSFScan.normalised()``: photons detected per
emitted photon (per binned pixel, from :meth:`EmissionModel.image`) × :data:`UNIT_SOURCE`, a unit
source emitting 10⁶ photons per ms detected at one count per photon. The registration fits the
data's own flux scale against it.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from multiprocessing import get_context

import numpy as np
from scipy.signal import fftconvolve

from cm2optics.calibrate.effects import Effect, split_key
from cm2optics.calibrate.simulate import OPTICAL, Values
from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, Focus, PSFSettings, SensorGrid, disc_kernel
from cm2optics.emission.scan import simulate_position
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind
from cm2optics.optics import first_order
from cm2optics.optics.lenslets import lens_cells

__all__ = [
    "UNIT_SOURCE",
    "TracerSimulator",
    "design_with",
    "fitted_source",
    "lenslet_vertices_px",
    "submit_rates",
    "traced_rates",
    "tracing_pool",
]

#: Counts per ms of a unit source per photon detected per emitted photon.
UNIT_SOURCE = 1e6
SENSOR_SIDE = {"stray_light", "pixel_crosstalk", "leakage_background"}
#: Optical effects that change the foci's shape, traced; the others move or scale traced foci.
RETRACED = {"mla_spacing", "vignetting", "source_profile", "mla_tilt", "sensor_tilt", "partial_lenslets"}


def design_with(
    design: SystemDesign, values: Values, offset_px: tuple[float, float] = (0.0, 0.0), pitch_um: float = 0.0
) -> SystemDesign:
    """``design`` with the optical effects in ``values`` (effect key → parameters) written into its
    fields (see the module docstring) and the frame offset (row, col binned px of ``pitch_um``
    µm) as a sensor offset. Sensor-side effects and the source's profile and size are not design
    fields of the device and are left out."""
    built = design.as_built
    changes: dict[str, object] = {}
    decenter = [list(built.lenslet_offset_mm(j)) for j in range(design.mla.rows * design.mla.cols)]
    transmission = [built.transmission(j) for j in range(design.mla.rows * design.mla.cols)]
    sides, border = list(design.mla.partial_sides), design.mla.partial_border_mm
    for key, p in values.items():
        name, j = split_key(key)
        if name == "partial_lenslets" and p["border_mm"] > 0:
            sides = sides if j in sides else sides + [j]
            border = max(border, p["border_mm"])
            changes["mla.partial_sides"] = [str(side) for side in sides]
            changes["mla.partial_border_mm"] = border
        elif name in ("mla_tilt", "sensor_tilt"):
            for axis in ("x", "y"):
                field_name = f"as_built.{name}_{axis}_deg"
                changes[field_name] = getattr(built, f"{name}_{axis}_deg") + p[f"tilt_{axis}_deg"]
        elif name == "mla_decenter":
            changes["as_built.mla_decenter_x_mm"] = built.mla_decenter_x_mm + p["dx_mm"]
            changes["as_built.mla_decenter_y_mm"] = built.mla_decenter_y_mm + p["dy_mm"]
        elif name == "mla_rotation":
            changes["as_built.mla_rotation_deg"] = built.mla_rotation_deg + p["angle_deg"]
        elif name == "mla_spacing":
            changes["imaging.mla_to_sensor_mm"] = design.imaging.mla_to_sensor_mm + p["delta_mm"]
        elif name == "lenslet_pitch":
            changes["as_built.lenslet_pitch_delta_mm"] = built.lenslet_pitch_delta_mm + p["delta_mm"]
        elif name == "lenslet_decenter":
            decenter[j] = [decenter[j][0] + p["dx_mm"], decenter[j][1] + p["dy_mm"]]
            changes["as_built.lenslet_decenter_mm"] = decenter
        elif name == "lenslet_transmission":
            transmission[j] *= p["transmission"]
            changes["as_built.lenslet_transmission"] = transmission
        elif name == "vignetting":
            changes["as_built.vignetting_radius_delta_mm"] = built.vignetting_radius_delta_mm + p["radius_delta_mm"]
    if offset_px != (0.0, 0.0):
        changes["as_built.sensor_offset_x_um"] = built.sensor_offset_x_um - offset_px[1] * pitch_um
        changes["as_built.sensor_offset_y_um"] = built.sensor_offset_y_um - offset_px[0] * pitch_um
    return design.with_changes(changes) if changes else design


def source_for(values: Values, base: PointSource) -> PointSource:
    """The calibration source ``base`` (the one the scan says it used) with ``values``'
    ``source_profile`` on top: its relative intensity × exp(−2·falloff·θ²). A Gaussian (or
    isotropic) base stays a Gaussian of 1/e² half-angle θ' with 1/θ'² = 1/θ² + falloff (at most
    180°); any other base, or a profile that would widen an isotropic one, becomes a table
    sampled every degree."""
    falloff = values.get("source_profile", {}).get("falloff_per_rad2", 0.0)
    profile = base.profile
    if falloff == 0.0:
        return base
    if profile.kind in (ProfileKind.GAUSSIAN, ProfileKind.ISOTROPIC):
        inverse = falloff + (math.radians(profile.parameter) ** -2 if profile.kind is ProfileKind.GAUSSIAN else 0.0)
        if inverse > 0:
            half_angle = min(math.degrees(1.0 / math.sqrt(inverse)), 180.0)
            return PointSource(base.diameter_um, AngularProfile(ProfileKind.GAUSSIAN, max(half_angle, 1.0)))
    angles = np.arange(91.0)
    theta = np.radians(angles)
    relative = profile.relative_intensity(theta) * np.exp(-2.0 * falloff * theta**2)
    return PointSource(
        base.diameter_um, AngularProfile(ProfileKind.TABLE, 0.0, tuple(angles), tuple(map(float, relative)))
    )


def fitted_source(values: Values, base: PointSource) -> PointSource:
    """The calibration source ``base`` with the fitted ``source_profile`` and ``source_size`` of
    ``values`` (what the scan's source was, as far as the fit tells)."""
    diameter = values.get("source_size", {}).get("diameter_um", base.diameter_um)
    return replace(source_for(values, base), diameter_um=float(diameter))


@dataclass(frozen=True)
class _Traced:
    """One traced focus kept for re-use: its lenslet (index into the optics' lenslets), its ePSF
    cropped to where it holds light (float32, fine samples 1/S px apart), the fine (row, col) of
    the crop's [0, 0] (fine index u is the pixel coordinate u/S), and its rays' centroid (x, y) mm."""

    lenslet: int
    epsf: np.ndarray
    origin: tuple[int, int]
    ray_centroid_mm: tuple[float, float]
    ray_power: float


def _crop(focus: Focus, oversample: int) -> _Traced:
    """The focus's ePSF cut to the box where it exceeds 10⁻⁷ of its peak (the window's empty
    diffraction margin dropped; the light outside is below 10⁻⁵ of the focus)."""
    epsf = focus.epsf
    lit = epsf > 1e-7 * float(epsf.max()) if epsf.size and epsf.max() > 0 else np.zeros(epsf.shape, bool)
    if not lit.any():
        return _Traced(focus.lenslet, np.zeros((0, 0), np.float32), (0, 0), focus.ray_centroid_mm, 0.0)
    rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
    a0, a1, b0, b1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    crop = np.ascontiguousarray(epsf[a0:a1, b0:b1], np.float32)
    origin = (oversample * focus.row0 + int(a0), oversample * focus.col0 + int(b0))
    return _Traced(focus.lenslet, crop, origin, focus.ray_centroid_mm, focus.ray_power)


def source_disc_um(values: Values, base: PointSource) -> float:
    """The diameter (µm, object space) of the disc that, convolved with foci traced with the
    calibration source ``base``, gives those of the ``source_size`` in ``values``: √(d² − d₀²),
    d₀ the traced source's diameter — exact in the second moment (a disc's, (d·m)²/16 per axis,
    adds), and in shape as d₀ ≪ d (a declared pinhole of a few µm); 0 without the effect (or a
    size at or below the declared one)."""
    size = values.get("source_size")
    if size is None:
        return 0.0
    return math.sqrt(max(size["diameter_um"] ** 2 - base.diameter_um**2, 0.0))


def _blurred(traced: _Traced, diameter_px: float, oversample: int) -> _Traced:
    """``traced`` convolved with a uniform disc ``diameter_px`` binned pixels across (its ePSF
    samples lie 1/``oversample`` px apart; the disc sampled on them, area-weighted)."""
    kernel = disc_kernel(diameter_px, 1.0 / oversample)
    if kernel is None or traced.epsf.size == 0:
        return traced
    half = kernel.shape[0] // 2
    epsf = np.clip(fftconvolve(traced.epsf, kernel.astype(np.float32), mode="full"), 0.0, None).astype(np.float32)
    origin = (traced.origin[0] - half, traced.origin[1] - half)
    return replace(traced, epsf=epsf, origin=origin)


def _axis_samples(origin: int, length: int, shift: float, oversample: int, size: int):
    """Output pixels and linear-interpolation taps along one axis for an ePSF of ``length`` fine
    samples starting at fine index ``origin``, moved by ``shift`` px, on an axis of ``size`` px:
    (pixels, index of the first tap into the ePSF padded by one zero each side, weight of the
    second tap). Pixel m samples the ePSF at the pixel coordinate m − shift."""
    s = oversample * shift
    k = math.floor(s)
    f = s - k
    first = max(int(math.floor((origin + k - 1) / oversample)), 0)
    last = min(int(math.ceil((origin + k + length + 1) / oversample)), size - 1)
    pixels = np.arange(first, last + 1)
    index = oversample * pixels - origin - k  # fine index at weight 1 − f; index − 1 at weight f
    return pixels, np.clip(index + 1, 0, length + 1), f


def _render(frame: np.ndarray, traced: _Traced, shift_px: tuple[float, float], scale: float, oversample: int) -> None:
    """Add ``scale`` × the focus moved by ``shift_px`` (row, col) px into ``frame`` (in place): its
    ePSF sampled at the pixel centres, linear between fine samples 1/S px apart."""
    if traced.epsf.size == 0 or scale == 0:
        return
    length_r, length_c = traced.epsf.shape
    rows, ir, fr = _axis_samples(traced.origin[0], length_r, shift_px[0], oversample, frame.shape[0])
    cols, ic, fc = _axis_samples(traced.origin[1], length_c, shift_px[1], oversample, frame.shape[1])
    if rows.size == 0 or cols.size == 0:
        return
    padded = np.pad(traced.epsf, 1)
    lower_r, lower_c = np.clip(ir - 1, 0, length_r + 1), np.clip(ic - 1, 0, length_c + 1)
    along_rows = (1.0 - fr) * padded[ir] + fr * padded[lower_r]
    patch = (1.0 - fc) * along_rows[:, ic] + fc * along_rows[:, lower_c]
    frame[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1] += scale * patch


@dataclass
class TracerSimulator:
    """The emission tracer as a :class:`~cm2optics.calibrate.simulate.Simulator` (module docstring).

    design: the nominal design (its own ``as_built`` values are the starting point; effects add
        to them). binning: sensor pixels per image pixel (1–16). source: the calibration source
        the scan says it used (default: an isotropic point); the ``source_profile`` effect
        multiplies its profile. settings: PSF sampling (None: ``PSFSettings(binning)``; its
        binning and oversampling are set to ``binning`` and ``oversample``). oversample: ePSF
        samples per pixel along each axis (2–16) for moving traced foci (None: ``binning``, so
        that the samples lie one sensor pixel apart, 2.4 µm for cm2-v2, at any binning).
        cache_mib: traced foci kept, MiB (least recently used dropped first). anchor: values of
        the moving effects that are traced too (:meth:`trace_at`); only departures from them are
        applied to traced foci.

    Effects that move a lenslet's vertex in the plane of the array (``mla_decenter``,
    ``mla_rotation``, ``lenslet_pitch``, ``lenslet_decenter``) move its focus rigidly by
    (1 + m)·d (d the vertex's displacement, m the chief-ray magnification at the source's height);
    ``lenslet_transmission`` scales it; the frame offset moves every focus; a calibration source
    larger than the traced one (``source_size``) blurs it by the extra disc's image
    (:func:`source_disc_um` × the chief-ray magnification at the source's depth). These are applied to
    the traced foci of the design without them, each focus's ePSF sampled at its moved pixel
    centres (exact for undersampled foci, where resampling the image would not be). The other
    optical effects (``mla_spacing``, ``vignetting``, ``source_profile``, the tilts, partial lenslets)
    change the foci's shape and are traced; a traced design's foci are cached by (design, source, position).
    """

    design: SystemDesign
    binning: int = 8
    source: PointSource = field(default_factory=lambda: PointSource(0.0, AngularProfile(ProfileKind.ISOTROPIC)))
    settings: PSFSettings | None = None
    oversample: int | None = None
    cache_mib: float = 1024.0
    anchor: Values = field(default_factory=dict)
    _models: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False)
    _foci: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False)
    _bytes: int = field(default=0, init=False, repr=False)
    traced_positions: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.oversample is None:
            self.oversample = max(2, min(16, self.binning))
        if not (isinstance(self.oversample, int) and 2 <= self.oversample <= 16):
            raise ValueError(f"oversample = {self.oversample!r}: must be an integer within 2–16")
        base = self.settings or PSFSettings(binning=self.binning)
        self.settings = replace(base, binning=self.binning, oversample=self.oversample)
        self.grid = SensorGrid.of(self.design, self.binning)

    # -- the protocol ----------------------------------------------------------------------------
    @property
    def lenslets(self) -> int:
        return self.design.mla.rows * self.design.mla.cols

    @property
    def pixel_um(self) -> float:
        return self.design.sensor.pixel_um * self.binning

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape

    def supports(self, effect: Effect) -> bool:
        return effect.name in OPTICAL or effect.name in SENSOR_SIDE

    @property
    def retraced(self) -> frozenset[str]:
        """Effects that cost a fresh trace of every position (the attribution linearises them)."""
        return frozenset(RETRACED)

    def pitch_px(self) -> float:
        """Distance between neighbouring foci of an on-axis source, px: (1 + m) × the lenslet pitch."""
        pitch_mm = self.design.mla.pitch_mm + self.design.as_built.lenslet_pitch_delta_mm
        return (1.0 + first_order.magnification(self.design)) * pitch_mm * 1000.0 / self.pixel_um

    def rates(
        self, positions_mm: np.ndarray, values: Values, offset_px: tuple[float, float] = (0.0, 0.0)
    ) -> np.ndarray:
        """Images (N, y, x) in counts per ms of a unit source with the effects in ``values`` and
        the sensor displaced by ``offset_px`` (row, col) px (see the class docstring)."""
        optical = {k: v for k, v in values.items() if k.partition("[")[0] not in SENSOR_SIDE}
        traced = {k: v for k, v in optical.items() if k.partition("[")[0] in RETRACED}
        base = design_with(self.design, {**self.anchor, **traced})
        model = self._model(base, source_for(traced, self.source))
        disc_um = source_disc_um(optical, self.source)
        moved = design_with(self.design, optical)
        vertex_shift = _vertices_mm(moved) - _vertices_mm(base)  # (cells, 2) x, y mm
        before, after = _transmissions(base), _transmissions(moved)
        transmission = np.divide(after, before, out=np.zeros_like(after), where=before > 0)
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        out = np.zeros((len(positions),) + self.shape, np.float32)
        frame = np.zeros(self.shape)
        pitch_mm = self.grid.pitch_mm
        for i, position in enumerate(positions):
            frame[:] = 0.0
            device = model.device_point_mm(self._in_design(model, position))
            magnification = first_order.chief_ray_magnification(base, float(device[2]))
            gain = 1.0 + magnification
            disc_px = disc_um * magnification / self.pixel_um  # the source's extra disc, binned px across
            for focus in self._traced(model, position):
                if disc_px > 0:
                    focus = _blurred(focus, disc_px, self.oversample)
                dx, dy = gain * vertex_shift[focus.lenslet] / pitch_mm
                shift = (offset_px[0] + dy, offset_px[1] + dx)
                _render(frame, focus, shift, transmission[focus.lenslet], self.oversample)
            out[i] = frame * UNIT_SOURCE
        return out

    def trace_at(self, values: Values) -> None:
        """Trace the moving effects (decentres, rotation, pitch, transmissions) of ``values`` from
        now on, so that images near them are exact traces and only small departures are applied
        to traced foci."""
        self.anchor = {
            k: dict(v)
            for k, v in values.items()
            if k.partition("[")[0] not in RETRACED and k.partition("[")[0] not in SENSOR_SIDE
        }

    def focus_centres_px(self, positions_mm: np.ndarray) -> np.ndarray:
        """(N, J, 2) (row, col) px of each full lenslet's focus in the nominal design: the traced
        rays' power-weighted centroid where the lenslet sends light onto the sensor, else the
        chief ray through its vertex (first-order magnification at the source's height)."""
        model = self._model(self.design, self.source)
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        cols = self.design.mla.cols
        out = np.empty((len(positions), self.lenslets, 2))
        for i, (x, y, z) in enumerate(positions):
            m = first_order.chief_ray_magnification(self.design, first_order.object_z_to_height_mm(self.design, z))
            for cell in lens_cells(self.design.mla, self.design.as_built):
                if not cell.partial:
                    sx, sy = cell.vertex_x - m * (x - cell.vertex_x), cell.vertex_y - m * (y - cell.vertex_y)
                    out[i, cell.row * cols + cell.col] = self.grid.row(sy), self.grid.col(sx)
            for focus in self._traced(model, np.array([x, y, z])):
                lenslet = model.optics.lenslets[focus.lenslet]
                if not lenslet.partial and focus.ray_power > 0:
                    cx, cy = focus.ray_centroid_mm
                    out[i, lenslet.row * cols + lenslet.col] = self.grid.row(cy), self.grid.col(cx)
        return out

    # -- helpers -----------------------------------------------------------------------------
    def _in_design(self, model: EmissionModel, position: np.ndarray) -> np.ndarray:
        """A position (object space of the nominal design, mm) in ``model``'s design's object space."""
        shift = first_order.object_plane_z_mm(model.design) - first_order.object_plane_z_mm(self.design)
        return np.array([position[0], position[1], position[2] + shift])

    def _model(self, design: SystemDesign, source: PointSource) -> EmissionModel:
        key = (design, source)
        model = self._models.get(key)
        if model is None:
            model = EmissionModel(design, source, settings=self.settings)
            self._models[key] = model
            while len(self._models) > 16:
                self._models.popitem(last=False)
        self._models.move_to_end(key)
        return model

    def _traced(self, model: EmissionModel, position: np.ndarray) -> list[_Traced]:
        """The traced foci of ``position`` (nominal object space, mm) under ``model`` (cached)."""
        key = (model.design, model.source, tuple(round(float(v), 9) for v in position))
        foci = self._foci.get(key)
        if foci is None:
            traced = simulate_position(model, self._in_design(model, position))
            foci = [_crop(f, self.oversample) for f in traced]
            self.traced_positions += 1
            self._foci[key] = foci
            self._bytes += sum(f.epsf.nbytes for f in foci)
            while self._bytes > self.cache_mib * 2**20 and len(self._foci) > 1:
                _, dropped = self._foci.popitem(last=False)
                self._bytes -= sum(f.epsf.nbytes for f in dropped)
        self._foci.move_to_end(key)
        return foci


def _vertices_mm(design: SystemDesign) -> np.ndarray:
    """(cells, 2) vertex (x, y) mm of every cell of the array as built, in the tracer's order."""
    return np.array([(c.vertex_x, c.vertex_y) for c in lens_cells(design.mla, design.as_built)])


def _transmissions(design: SystemDesign) -> np.ndarray:
    """(cells,) as-built transmission of every cell (partial cells: 1), in the tracer's order."""
    cols = design.mla.cols
    return np.array(
        [
            1.0 if c.partial else design.as_built.transmission(c.row * cols + c.col)
            for c in lens_cells(design.mla, design.as_built)
        ]
    )


def _rates_task(
    spec: tuple, positions_mm: np.ndarray, values: Values, with_centres: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """Worker: the images (and the nominal focus centres) of a chunk of positions, traced by a
    simulator of ``spec`` (design, binning, source, settings, oversample, anchor; an empty
    cache), Dr.Jit on one thread (one worker per core)."""
    from cm2optics.emission.scan import _set_jit_threads

    _set_jit_threads(1)
    design, binning, source, settings, oversample, anchor = spec
    simulator = TracerSimulator(design, binning, source, settings, oversample, anchor=anchor)
    centres = simulator.focus_centres_px(positions_mm) if with_centres else None
    return simulator.rates(positions_mm, values), centres


#: Niceness the tracing workers add to their own: the process that submitted them (the
#: attribution, the analyses: the path every result waits on) keeps a core, the workers share the rest.
WORKER_NICENESS = 5


@contextmanager
def tracing_pool(workers: int) -> Iterator[ProcessPoolExecutor | None]:
    """``workers`` spawned worker processes for :func:`submit_rates`, at a lower priority than
    this process (:data:`WORKER_NICENESS`) (None, and no process, for ``workers`` ≤ 1; processes
    start with the first task submitted). On leaving, tasks not yet started are dropped (an
    error does not wait for a whole scan's trace)."""
    if workers <= 1:
        yield None
        return
    # os.nice itself as the initializer: the workers' priority is lowered before they import
    # anything (threads started later inherit it)
    pool = ProcessPoolExecutor(
        workers, mp_context=get_context("spawn"), initializer=os.nice, initargs=(WORKER_NICENESS,)
    )
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def submit_rates(
    pool: ProcessPoolExecutor | None,
    simulator: TracerSimulator,
    positions_mm: np.ndarray,
    values: Values,
    *,
    with_centres: bool = False,
    here: np.ndarray | None = None,
    chunk: int = 8,
) -> Callable[[], tuple[np.ndarray, np.ndarray | None]]:
    """Start ``simulator.rates(positions_mm, values)`` (and, ``with_centres``, its nominal
    ``focus_centres_px``): the positions indexed by ``here`` (all of them without a ``pool``)
    traced now in this process, re-using its cache, the others by the ``pool``'s processes,
    ``chunk`` per task, with the simulator's settings and anchor as they are now. Returns the
    function that waits for them: (images (N, y, x), centres (N, J, 2) or None), in order."""
    positions = np.asarray(positions_mm, float).reshape(-1, 3)
    local = (
        np.ones(len(positions), bool)
        if pool is None
        else np.isin(np.arange(len(positions)), here if here is not None else [])
    )
    remote = np.flatnonzero(~local)
    s = simulator
    values = {k: dict(v) for k, v in values.items()}
    tasks = [remote[i : i + chunk] for i in range(0, len(remote), chunk)]
    futures = []
    if tasks:
        spec = (s.design, s.binning, s.source, s.settings, s.oversample, {k: dict(v) for k, v in s.anchor.items()})
        futures = [pool.submit(_rates_task, spec, positions[task], values, with_centres) for task in tasks]
    mine = np.flatnonzero(local)
    rates = np.empty((len(positions),) + s.shape, np.float32)
    centres = np.empty((len(positions), s.lenslets, 2)) if with_centres else None
    rates[mine] = s.rates(positions[mine], values)
    if with_centres:
        centres[mine] = s.focus_centres_px(positions[mine])

    def wait() -> tuple[np.ndarray, np.ndarray | None]:
        for task, future in zip(tasks, futures, strict=True):
            rates[task], task_centres = future.result()
            if with_centres:
                centres[task] = task_centres
        return rates, centres

    return wait


def traced_rates(
    simulator: TracerSimulator,
    positions_mm: np.ndarray,
    values: Values,
    *,
    workers: int = 1,
    with_centres: bool = False,
    chunk: int = 8,
) -> tuple[np.ndarray, np.ndarray | None]:
    """``simulator.rates(positions_mm, values)`` and, ``with_centres``, its nominal
    ``focus_centres_px`` — in this process (``workers`` 1, the simulator's cache filled), or
    traced by ``workers`` processes, ``chunk`` positions per task (for a whole scan: every
    position is traced once, so a shared cache gains nothing)."""
    positions = np.asarray(positions_mm, float).reshape(-1, 3)
    with tracing_pool(workers if len(positions) > chunk else 1) as pool:
        return submit_rates(pool, simulator, positions, values, with_centres=with_centres, chunk=chunk)()


def lenslet_vertices_px(design: SystemDesign, binning: int) -> np.ndarray:
    """(J, 2) (row, col) px, at ``binning``, below each full lenslet's vertex of ``design``: where
    its focus lands for a source straight in front of it (any depth)."""
    grid = SensorGrid.of(design, binning)
    out = np.full((design.mla.rows * design.mla.cols, 2), np.nan)
    for cell in lens_cells(design.mla, design.as_built):
        if not cell.partial:
            out[cell.row * design.mla.cols + cell.col] = grid.row(cell.vertex_y), grid.col(cell.vertex_x)
    return out
