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
lenslet_pitch (delta_mm)    ``as_built.lenslet_pitch_delta_mm``
lenslet_decenter[j]         ``as_built.lenslet_decenter_mm[j]``
lenslet_transmission[j]     ``as_built.lenslet_transmission[j]``
vignetting                  ``as_built.vignetting_radius_delta_mm``
source_profile              the calibration source's Gaussian profile (not the device's:
                            falloff f → 1/e² half-angle 1/√f rad, at most 180°; 0: isotropic)
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
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from cm2optics.calibrate.effects import Effect
from cm2optics.calibrate.simulate import OPTICAL, Values
from cm2optics.design import SystemDesign
from cm2optics.emission.psf import EmissionModel, PSFSettings, SensorGrid, add_focus
from cm2optics.emission.scan import simulate_position
from cm2optics.emission.source import AngularProfile, PointSource, ProfileKind
from cm2optics.optics import first_order
from cm2optics.optics.lenslets import lens_cells

__all__ = ["UNIT_SOURCE", "TracerSimulator", "design_with"]

#: Counts per ms of a unit source per photon detected per emitted photon.
UNIT_SOURCE = 1e6
SENSOR_SIDE = {"stray_light", "pixel_crosstalk", "leakage_background"}


def design_with(
    design: SystemDesign, values: Values, offset_px: tuple[float, float] = (0.0, 0.0), pitch_um: float = 0.0
) -> SystemDesign:
    """``design`` with the optical effects in ``values`` (effect key → parameters) written into its
    fields (see the module docstring) and the frame offset (row, col binned px of ``pitch_um``
    µm) as a sensor offset. Sensor-side effects and the source profile are not design fields of
    the device and are left out."""
    built = design.as_built
    changes: dict[str, object] = {}
    decenter = [list(built.lenslet_offset_mm(j)) for j in range(design.mla.rows * design.mla.cols)]
    transmission = [built.transmission(j) for j in range(design.mla.rows * design.mla.cols)]
    for key, p in values.items():
        name, _, index = key.partition("[")
        j = int(index[:-1]) if index else None
        if name == "mla_decenter":
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


def source_for(values: Values, diameter_um: float) -> PointSource:
    """The calibration source of ``values``' ``source_profile`` (isotropic without it)."""
    falloff = values.get("source_profile", {}).get("falloff_per_rad2", 0.0)
    if falloff <= 0:
        return PointSource(diameter_um, AngularProfile(ProfileKind.ISOTROPIC))
    half_angle = min(math.degrees(1.0 / math.sqrt(falloff)), 180.0)
    return PointSource(diameter_um, AngularProfile(ProfileKind.GAUSSIAN, half_angle))


@dataclass
class TracerSimulator:
    """The emission tracer as a :class:`~cm2optics.calibrate.simulate.Simulator` (module docstring).

    design: the nominal design (its own ``as_built`` values are the starting point; effects add
        to them). binning: sensor pixels per image pixel (1–16). source_diameter_um: the
        calibration source's diameter, µm. settings: PSF sampling (None: ``PSFSettings(binning)``;
        its binning must equal ``binning``). cache: traced models kept (one per design and source).
    """

    design: SystemDesign
    binning: int = 8
    source_diameter_um: float = 0.0
    settings: PSFSettings | None = None
    cache: int = 8
    _models: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False)
    _centres: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.settings is None:
            self.settings = PSFSettings(binning=self.binning)
        elif self.settings.binning != self.binning:
            self.settings = replace(self.settings, binning=self.binning)
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

    def pitch_px(self) -> float:
        """Distance between neighbouring foci of an on-axis source, px: (1 + m) × the lenslet pitch."""
        pitch_mm = self.design.mla.pitch_mm + self.design.as_built.lenslet_pitch_delta_mm
        return (1.0 + first_order.magnification(self.design)) * pitch_mm * 1000.0 / self.pixel_um

    def rates(
        self, positions_mm: np.ndarray, values: Values, offset_px: tuple[float, float] = (0.0, 0.0)
    ) -> np.ndarray:
        """Images (N, y, x) in counts per ms of a unit source, the effects in ``values`` traced and
        the sensor displaced by ``offset_px`` (row, col) px (traced there, not resampled)."""
        offset = (float(offset_px[0]), float(offset_px[1]))
        optical = {k: v for k, v in values.items() if k.partition("[")[0] not in SENSOR_SIDE}
        design = design_with(self.design, optical, offset, self.pixel_um)
        model = self._model(design, source_for(optical, self.source_diameter_um))
        shift = first_order.object_plane_z_mm(model.design) - first_order.object_plane_z_mm(self.design)
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        out = np.zeros((len(positions),) + self.shape, np.float32)
        for i, (x, y, z) in enumerate(positions):
            frame = np.zeros(self.shape)
            for focus in simulate_position(model, np.array([x, y, z + shift])):
                add_focus(frame, focus)
            out[i] = frame * UNIT_SOURCE
        return out

    def focus_centres_px(self, positions_mm: np.ndarray) -> np.ndarray:
        """(N, J, 2) (row, col) px of each full lenslet's focus in the nominal design: the traced
        rays' power-weighted centroid where the lenslet sends light onto the sensor, else the
        chief ray through its vertex (first-order magnification at the source's height)."""
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        return np.stack([self._centres_of((float(x), float(y), float(z))) for x, y, z in positions])

    # -- helpers -----------------------------------------------------------------------------
    def _model(self, design: SystemDesign, source: PointSource) -> EmissionModel:
        key = (design, source)
        model = self._models.get(key)
        if model is None:
            model = EmissionModel(design, source, settings=self.settings)
            self._models[key] = model
            while len(self._models) > self.cache:
                self._models.popitem(last=False)
        self._models.move_to_end(key)
        return model

    def _centres_of(self, position: tuple[float, float, float]) -> np.ndarray:
        if position not in self._centres:
            model = self._model(self.design, source_for({}, self.source_diameter_um))
            x, y, z = position
            m = first_order.chief_ray_magnification(self.design, first_order.object_z_to_height_mm(self.design, z))
            cols = self.design.mla.cols
            centres = np.empty((self.lenslets, 2))
            for cell in lens_cells(self.design.mla, self.design.as_built):
                if not cell.partial:
                    sx, sy = cell.vertex_x - m * (x - cell.vertex_x), cell.vertex_y - m * (y - cell.vertex_y)
                    centres[cell.row * cols + cell.col] = self.grid.row(sy), self.grid.col(sx)
            for focus in simulate_position(model, np.array(position)):
                lenslet = model.optics.lenslets[focus.lenslet]
                if not lenslet.partial and focus.ray_power > 0:
                    cx, cy = focus.ray_centroid_mm
                    centres[lenslet.row * cols + lenslet.col] = self.grid.row(cy), self.grid.col(cx)
            self._centres[position] = centres
        return self._centres[position]
