"""A point source → its image on the sensor: nine foci, each traced, diffracted and pixelated.

:class:`EmissionModel` holds what does not change from one source position to the next (the
design's emission path, the wavelength bands, the source, the sampling settings);
:meth:`EmissionModel.foci` turns one source position into one :class:`Focus` per lenslet that
sends light to the sensor, and :meth:`EmissionModel.image` places them on the sensor frame.

Per position, for every visible lenslet and every band, together in two vectorised traces
(:mod:`.trace`): a coarse grid of rays finds each lenslet's reference sphere, pupil map, spot,
window and RMS wavefront error; then a grid uniform on the reference sphere gives the wavefront
that the Debye–Wolf integral turns into the PSF (:mod:`.wavefront`) — or, for a lenslet with more
than ``geometric_waves`` of aberration, a launch grid gives the ray density (geometric branch,
all bands at once). Bands that carry less than :data:`NEGLIGIBLE_BAND` of a lenslet's light (the
spectrum's tails, which the filter and the film all but stop) are left out. The PSF is evaluated
on sub-pixels (at most ``subpixel_um`` apart, so that the pixel integral is sampled above
Nyquist), summed over bands, convolved with the source's geometric image (a disc of
|m|·diameter, m the chief-ray magnification at the source's depth) and summed into pixels.

Units: a PSF pixel holds the number of photons detected (photo-electrons) in it per photon the
source emits into its hemisphere. Coordinates:

* source positions in object space (``x_mm, y_mm`` from the central lenslet's axis, ``z_mm``
  from the nominal focal plane, +z towards the device), as in PSF scans (DESIGN.md);
* the sensor frame of the device: the image's column index runs along +x, its row index along
  +y, and the frame's centre is the optical axis (:class:`SensorGrid`). Each lenslet forms an
  inverted image (magnification ≈ −0.58), so a source moved +x moves every focus towards −x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.signal import fftconvolve

from cm2optics.design import SystemDesign
from cm2optics.design.materials import refractive_index
from cm2optics.emission.optics import EmissionOptics, emission_optics
from cm2optics.emission.source import PointSource, calibration_pinhole
from cm2optics.emission.spectral import SpectralBands, spectral_bands
from cm2optics.emission.trace import RayBatch, TracedRays, default_engine, paraxial_reach_mm, trace_rays
from cm2optics.emission.wavefront import PupilMap, debye_fft, fft_size, fit_pupil_map, mft, solve_least_squares
from cm2optics.optics import first_order
from cm2optics.optics.tilt import rotate
from cm2optics.spectra.spectrum import Spectrum

#: Fraction of a lenslet's light (all bands) below which a band is left out of its focus.
NEGLIGIBLE_BAND = 1e-4

__all__ = [
    "NEGLIGIBLE_BAND",
    "EmissionModel",
    "Focus",
    "Pupil",
    "PSFSettings",
    "SensorGrid",
]


@dataclass(frozen=True)
class SensorGrid:
    """The pixel grid of saved images: the sensor binned by ``binning``.

    width_px, height_px: sensor pixels along x and y. pixel_um: sensor pitch, µm. binning: sensor
    pixels per saved pixel along each axis (1–16); trailing sensor pixels that do not fill a
    binned pixel are dropped. Binned pixel (row, col) covers sensor rows row·B … row·B + B − 1;
    its centre lies at x = (col·B + (B − 1)/2 − (width_px − 1)/2) · pixel + offset_x (and likewise y).
    offset_x_um, offset_y_um: the sensor displaced along +x, +y relative to the optics, µm
    (``as_built.sensor_offset_*_um``; the image moves the other way on the pixel grid).
    """

    width_px: int
    height_px: int
    pixel_um: float
    binning: int = 1
    offset_x_um: float = 0.0
    offset_y_um: float = 0.0

    def __post_init__(self) -> None:
        if not (isinstance(self.binning, int) and 1 <= self.binning <= 16):
            raise ValueError(f"binning = {self.binning!r}: must be an integer within 1–16")
        if self.width_px // self.binning < 1 or self.height_px // self.binning < 1:
            raise ValueError(f"binning = {self.binning}: larger than the sensor")

    @classmethod
    def of(cls, design: SystemDesign, binning: int = 1) -> SensorGrid:
        s, built = design.sensor, design.as_built
        return cls(s.width_px, s.height_px, s.pixel_um, binning, built.sensor_offset_x_um, built.sensor_offset_y_um)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of a saved image."""
        return self.height_px // self.binning, self.width_px // self.binning

    @property
    def pitch_mm(self) -> float:
        """Pitch of the saved pixels, mm."""
        return self.pixel_um * self.binning / 1000.0

    def x_mm(self, col: np.ndarray | float) -> np.ndarray:
        """x (mm, device frame) of the centre of binned column ``col``."""
        b = self.binning
        return (
            (np.asarray(col, dtype=float) * b + (b - 1) / 2 - (self.width_px - 1) / 2) * self.pixel_um
            + self.offset_x_um
        ) / 1000.0

    def y_mm(self, row: np.ndarray | float) -> np.ndarray:
        """y (mm, device frame) of the centre of binned row ``row``."""
        b = self.binning
        return (
            (np.asarray(row, dtype=float) * b + (b - 1) / 2 - (self.height_px - 1) / 2) * self.pixel_um
            + self.offset_y_um
        ) / 1000.0

    def col(self, x_mm: np.ndarray | float) -> np.ndarray:
        """Fractional binned column whose centre lies at ``x_mm`` (mm)."""
        b = self.binning
        x_um = np.asarray(x_mm, dtype=float) * 1000.0 - self.offset_x_um
        return ((x_um / self.pixel_um) + (self.width_px - 1) / 2 - (b - 1) / 2) / b

    def row(self, y_mm: np.ndarray | float) -> np.ndarray:
        """Fractional binned row whose centre lies at ``y_mm`` (mm)."""
        b = self.binning
        y_um = np.asarray(y_mm, dtype=float) * 1000.0 - self.offset_y_um
        return ((y_um / self.pixel_um) + (self.height_px - 1) / 2 - (b - 1) / 2) / b


@dataclass(frozen=True)
class PSFSettings:
    """Sampling of the PSF computation.

    binning: sensor pixels per saved pixel (1–16).
    band_nm: widest wavelength band, nm (1–100).
    coarse_rays: rays along each side of the coarse grid that finds each pupil (8–64).
    margin: room left around each geometric spot for diffraction, in units of λ/(2 NA') (2–40).
    subpixel_um: largest spacing of the samples that integrate a pixel, µm (0.2–5).
    geometric_waves: RMS wavefront error (waves, in any band) above which a lenslet's PSF is
        computed geometrically (:mod:`.wavefront`, step 5); ``inf`` forces diffraction everywhere (0.5–inf).
    geometric_rays: launch rays along each side of the grid of the geometric branch (16–512).
    engine: ``"drjit"`` or ``"numpy"`` (None: the fastest available).
    oversample: 1, or S > 1 to give every focus its effective PSF on a grid S times finer than
        the saved pixels as well (:mod:`.epsf`; the sub-samples per pixel are raised to a
        multiple of S) (1–16).
    """

    binning: int = 1
    band_nm: float = 10.0
    coarse_rays: int = 16
    margin: float = 6.0
    subpixel_um: float = 1.2
    geometric_waves: float = 5.0
    geometric_rays: int = 96
    engine: str | None = None
    oversample: int = 1

    def __post_init__(self) -> None:
        if not (isinstance(self.oversample, int) and 1 <= self.oversample <= 16):
            raise ValueError(f"oversample = {self.oversample!r}: must be an integer within 1–16")
        if not (isinstance(self.binning, int) and 1 <= self.binning <= 16):
            raise ValueError(f"binning = {self.binning!r}: must be an integer within 1–16")
        if not (math.isfinite(self.band_nm) and 1 <= self.band_nm <= 100):
            raise ValueError(f"band_nm = {self.band_nm!r}: must lie within 1–100 nm")
        if not (isinstance(self.coarse_rays, int) and 8 <= self.coarse_rays <= 64):
            raise ValueError(f"coarse_rays = {self.coarse_rays!r}: must be an integer within 8–64")
        if not (math.isfinite(self.margin) and 2 <= self.margin <= 40):
            raise ValueError(f"margin = {self.margin!r}: must lie within 2–40 (units of λ/2NA')")
        if not (math.isfinite(self.subpixel_um) and 0.2 <= self.subpixel_um <= 5):
            raise ValueError(f"subpixel_um = {self.subpixel_um!r}: must lie within 0.2–5 µm")
        if not (self.geometric_waves >= 0.5):
            raise ValueError(f"geometric_waves = {self.geometric_waves!r}: must be ≥ 0.5 waves (inf: never)")
        if not (isinstance(self.geometric_rays, int) and 16 <= self.geometric_rays <= 512):
            raise ValueError(f"geometric_rays = {self.geometric_rays!r}: must be an integer within 16–512")
        if self.engine not in (None, "drjit", "numpy"):
            raise ValueError(f"engine = {self.engine!r}: must be 'drjit', 'numpy' or None")


@dataclass(frozen=True, eq=False)
class Pupil:
    """The sampled pupil of one lenslet in one band for one source (see :mod:`.wavefront`).

    lenslet, band: indices. wavelength_mm: the band's wavelength, mm.
    l_axis, m_axis: (n_l,), (n_m,) direction cosines of the grid (centred: index (n − 1)/2 at the middle).
    spacing: ΔL = ΔM. amplitude: (n_m, n_l) |A| (√ of power per unit dL dM; 0 where blocked).
    wavefront_mm: (n_m, n_l) W relative to (x_ref, y_ref), power-weighted mean removed, mm.
    x_ref_mm, y_ref_mm: the reference point on the sensor plane (the centre of the reference sphere), mm.
    power: photons detected per photon emitted (Σ |A|² ΔL ΔM).
    """

    lenslet: int
    band: int
    wavelength_mm: float
    l_axis: np.ndarray
    m_axis: np.ndarray
    spacing: float
    amplitude: np.ndarray
    wavefront_mm: np.ndarray
    x_ref_mm: float
    y_ref_mm: float
    power: float

    def field(self, aberration_free: bool = False) -> np.ndarray:
        """The complex pupil A·e^{ikW} (or A alone: the same aperture without aberrations)."""
        if aberration_free:
            return self.amplitude.astype(complex)
        return self.amplitude * np.exp(2j * math.pi / self.wavelength_mm * self.wavefront_mm)

    def intensity(self, x_mm: np.ndarray, y_mm: np.ndarray, aberration_free: bool = False) -> np.ndarray:
        """Irradiance (photons detected per emitted photon, per mm²) on the grid ``y_mm`` × ``x_mm``
        (absolute sensor-plane coordinates, mm), by a matrix Fourier transform."""
        return mft(
            self.field(aberration_free),
            self.l_axis,
            self.m_axis,
            np.asarray(x_mm, dtype=float) - self.x_ref_mm,
            np.asarray(y_mm, dtype=float) - self.y_ref_mm,
            self.wavelength_mm,
            self.spacing,
        )

    def rms_wavefront_waves(self) -> float:
        """RMS wavefront error over the pupil (power-weighted), piston and tilt removed, waves."""
        return _rms_waves(
            np.meshgrid(self.l_axis, self.m_axis)[0].ravel(),
            np.meshgrid(self.l_axis, self.m_axis)[1].ravel(),
            self.wavefront_mm.ravel(),
            (self.amplitude**2).ravel(),
            self.wavelength_mm,
        )


def sphere_coordinates(
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    direction: np.ndarray,
    opl_mm: np.ndarray,
    centre_mm: tuple[float, float],
    pupil_mm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where rays cross the reference sphere, as seen from its centre, and their path to it.

    The sphere is centred on (``centre_mm``, 0) on the sensor plane and passes through the exit
    pupil's centre ``pupil_mm`` (x, y, z; mm). Each ray, hitting the sensor plane at (x, y) with
    unit direction ``direction`` (n, 3) and optical path ``opl_mm``, is followed back to the sphere
    (point q). Returns (Lq, Mq, W): the x and y components of the unit vector from q to the centre
    (the Debye integral's variables) and the optical path from the source to q, mm.
    """
    cx, cy = centre_mm
    radius = math.sqrt((pupil_mm[0] - cx) ** 2 + (pupil_mm[1] - cy) ** 2 + pupil_mm[2] ** 2)
    px, py = x_mm - cx, y_mm - cy
    along = px * direction[:, 0] + py * direction[:, 1]
    t = along + np.sqrt(np.maximum(along * along - (px * px + py * py - radius * radius), 0.0))
    qx = px - t * direction[:, 0]
    qy = py - t * direction[:, 1]
    return -qx / radius, -qy / radius, opl_mm - t


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a · b without BLAS (whose threads cost milliseconds per call on a busy machine)."""
    return float(np.einsum("i,i->", a, b))


def _rms_waves(L: np.ndarray, M: np.ndarray, wave_mm: np.ndarray, weight: np.ndarray, wavelength_mm: float) -> float:
    ok = (weight > 0) & np.isfinite(wave_mm)
    if ok.sum() < 4:
        return float("nan")
    a = np.column_stack([np.ones(ok.sum()), L[ok] - L[ok].mean(), M[ok] - M[ok].mean()])
    sw = np.sqrt(weight[ok])
    coef = solve_least_squares(a * sw[:, None], wave_mm[ok] * sw)
    resid = wave_mm[ok] - a @ coef
    return float(np.sqrt(np.sum(weight[ok] * resid**2) / np.sum(weight[ok])) / wavelength_mm)


@dataclass(frozen=True, eq=False)
class Focus:
    """The image of a source through one lenslet, on the binned pixel grid.

    lenslet: index into :attr:`EmissionOptics.lenslets`. row0, col0: binned pixel of
    ``patch[0, 0]``. patch: photons detected per emitted photon, per binned pixel.
    ray_centroid_mm: power-weighted mean of the rays' hits on the sensor plane (x, y), mm.
    ray_power: photons detected per emitted photon according to the rays (before diffraction).
    geometric: whether the focus took the geometric branch (:mod:`.wavefront`, step 5).
    """

    lenslet: int
    row0: int
    col0: int
    patch: np.ndarray
    ray_centroid_mm: tuple[float, float]
    ray_power: float
    geometric: bool = False
    epsf: np.ndarray | None = None

    @property
    def energy(self) -> float:
        return float(self.patch.sum())

    def centroid_px(self) -> tuple[float, float]:
        """Intensity centroid (row, col) in binned pixels of the full frame."""
        total = self.patch.sum()
        if total <= 0:
            return float("nan"), float("nan")
        rows = np.arange(self.patch.shape[0]) + self.row0
        cols = np.arange(self.patch.shape[1]) + self.col0
        return float(self.patch.sum(axis=1) @ rows / total), float(self.patch.sum(axis=0) @ cols / total)


def disc_kernel(diameter: float, pitch: float, supersample: int = 8) -> np.ndarray | None:
    """A uniform disc of ``diameter`` sampled (area-weighted) on pixels of ``pitch`` (the same
    unit); sums to 1. None when the disc is under a quarter of a pixel across (a point)."""
    if diameter < 0.25 * pitch:
        return None
    half = int(math.ceil(diameter / 2 / pitch + 0.5))
    n = 2 * half + 1
    fine = (np.arange(n * supersample) + 0.5) / supersample - n / 2
    xx, yy = np.meshgrid(fine, fine)
    inside = (xx**2 + yy**2 <= (diameter / 2 / pitch) ** 2).astype(float)
    kernel = inside.reshape(n, supersample, n, supersample).sum(axis=(1, 3))
    return kernel / kernel.sum()


@dataclass(eq=False)
class _Pair:
    """Work record of one lenslet × band for one source (pass 1 → pass 2)."""

    lenslet: int
    band: int
    wavelength_mm: float
    pupil_map: PupilMap
    l_box: tuple[float, float]
    m_box: tuple[float, float]
    uv_box: tuple[float, float, float, float]
    spot: tuple[float, float, float, float]
    na: float
    waves: float
    geometric: bool = False
    rays: slice | None = None
    grid: tuple = ()
    pupil: Pupil | None = None
    power: float = 0.0
    centroid: tuple[float, float] = (0.0, 0.0)
    splat: np.ndarray | None = None
    reference: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class _Window:
    """A lenslet's output window: binned pixels r0…r1, c0…c1 (inclusive), q sub-samples each."""

    r0: int
    r1: int
    c0: int
    c1: int
    q: int
    xs: np.ndarray
    ys: np.ndarray

    @property
    def pitch_mm(self) -> float:
        return float(self.xs[1] - self.xs[0]) if len(self.xs) > 1 else float("nan")


class EmissionModel:
    """The emission path of a design, ready to image point sources (see the module docstring).

    design: the system. source: the point source (default: the paper's calibration pinhole).
    emission: source spectrum (default: the fluorophore, ``gfp-emission``). settings: sampling.
    filtered: apply the interference filter and film (False only for tests of their effect).
    """

    def __init__(
        self,
        design: SystemDesign,
        source: PointSource | None = None,
        emission: Spectrum | None = None,
        settings: PSFSettings | None = None,
        filtered: bool = True,
    ) -> None:
        self.design = design
        self.source = source if source is not None else calibration_pinhole()
        self.settings = settings if settings is not None else PSFSettings()
        self.optics: EmissionOptics = emission_optics(design)
        self.bands: SpectralBands = spectral_bands(design, emission, band_nm=self.settings.band_nm, filtered=filtered)
        self.grid = SensorGrid.of(design, self.settings.binning)
        self.engine = self.settings.engine or default_engine()
        lam = self.bands.wavelength_nm
        film = self.optics.film
        self._indices = np.column_stack(
            [
                refractive_index(self.optics.filter.material, lam),
                refractive_index(self.optics.lens_material, lam),
                refractive_index(film.material, lam) if film is not None else np.ones_like(lam),
            ]
        )
        self._visible = [c.index for c in self.optics.lenslets if self.optics.lenslet_visible(c)]
        weights = self.bands.table[:, 0, 0]
        self._mid_band = int(
            np.argmin(np.abs(self.bands.wavelength_nm - weights @ self.bands.wavelength_nm / weights.sum()))
        )
        self._q = max(1, int(math.ceil(self.grid.pitch_mm * 1000.0 / self.settings.subpixel_um)))
        S = self.settings.oversample
        self._q = S * int(math.ceil(self._q / S))

    # -- coordinates ---------------------------------------------------------------------------
    def device_point_mm(self, position_mm: tuple[float, float, float] | np.ndarray) -> np.ndarray:
        """Object-space position (x, y, z from the focal plane, +z towards the device; mm) → device frame."""
        p = np.asarray(position_mm, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"position_mm = {position_mm!r}: must be three finite numbers (x, y, z) in mm")
        height = self.optics.object_plane_z_mm - p[2]
        limit = self.optics.object_plane_z_mm - self.optics.filter.z1_mm - 0.05
        if p[2] > limit:
            raise ValueError(
                f"position z_mm = {p[2]:g}: the source would sit at {height:.3f} mm in the device frame, on or "
                f"inside the device (the filter's top face is at {self.optics.filter.z1_mm:.3f} mm): z_mm must be "
                f"< {limit:.3f} mm"
            )
        return np.array([p[0], p[1], height])

    # -- rays ----------------------------------------------------------------------------------
    def _batch(
        self,
        source: np.ndarray,
        u: np.ndarray,
        v: np.ndarray,
        lenslet: np.ndarray,
        band: np.ndarray,
        group: np.ndarray | None = None,
    ) -> RayBatch:
        """Rays from ``source`` (device frame, mm) at tangents ``u, v`` through ``lenslet`` in
        ``band`` (−1: the mid band, for the geometric branch), both per ray, or per group of rays
        with ``group`` (per ray) naming each ray's row."""
        lenslet, band = np.asarray(lenslet), np.asarray(band)
        n = self._indices[np.where(band >= 0, band, self._mid_band)]
        return RayBatch(np.broadcast_to(source, (len(lenslet), 3)), u, v, lenslet, n[:, 0], n[:, 1], n[:, 2], group)

    def _power_density(self, traced: TracedRays, u: np.ndarray, v: np.ndarray, band: np.ndarray) -> np.ndarray:
        """Photons detected per photon emitted, per unit (u, v) of launch tangent (0 where blocked).
        ``band`` −1 marks rays of the geometric branch, which carry all bands at once."""
        passed = traced.passed
        out = np.zeros(len(u))
        if not passed.any():
            return out
        u, v, band = u[passed], v[passed], band[passed]
        aoi_filter, aoi_film = traced.aoi_filter_rad[passed], traced.aoi_film_rad[passed]
        solid = (1.0 + u * u + v * v) ** -1.5
        intensity = self.source.profile.intensity_sr(aoi_filter)
        spectral = np.empty(len(u))
        single = band >= 0
        spectral[single] = self.bands.weight(band[single], aoi_filter[single], aoi_film[single])
        spectral[~single] = self.bands.total_weight(aoi_filter[~single], aoi_film[~single])
        out[passed] = intensity * solid * traced.fresnel[passed] * spectral
        return out

    def _coarse(self, source: np.ndarray, lenslets: list[int], bands: list[int]) -> list[_Pair]:
        """Pass 1: a coarse tangent grid over each lenslet per band → pupil maps, spots, boxes."""
        n1 = self.settings.coarse_rays
        grid = (np.arange(n1) + 0.5) / n1
        pairs_lb = [(k, b) for k in lenslets for b in bands]
        if not pairs_lb:
            return []
        us, vs = [], []
        optics = self.optics
        for k, b in pairs_lb:
            cell = optics.lenslets[k]
            reach = [
                paraxial_reach_mm(optics, source[2], self._indices[b, 0], z)
                for z in (optics.vertex_z_mm, optics.land_z_mm)
            ]
            ux = [(x - source[0]) / r for x in (cell.x0_mm, cell.x1_mm) for r in reach]
            vy = [(y - source[1]) / r for y in (cell.y0_mm, cell.y1_mm) for r in reach]
            lo_u, hi_u, lo_v, hi_v = min(ux), max(ux), min(vy), max(vy)
            pad_u, pad_v = 0.08 * (hi_u - lo_u), 0.08 * (hi_v - lo_v)
            uu, vv = np.meshgrid(
                lo_u - pad_u + grid * (hi_u - lo_u + 2 * pad_u), lo_v - pad_v + grid * (hi_v - lo_v + 2 * pad_v)
            )
            us.append(uu.ravel())
            vs.append(vv.ravel())
        u, v = np.concatenate(us), np.concatenate(vs)
        group = np.repeat(np.arange(len(pairs_lb)), n1 * n1)
        pair_band = np.array([b for _, b in pairs_lb])
        batch = self._batch(source, u, v, np.array([k for k, _ in pairs_lb]), pair_band, group)
        traced = trace_rays(optics, batch, self.engine)
        density = self._power_density(traced, u, v, pair_band[group])
        pairs = []
        for i, (k, b) in enumerate(pairs_lb):
            sl = slice(i * n1 * n1, (i + 1) * n1 * n1)
            ok, passed = traced.traced[sl], traced.passed[sl] & (density[sl] > 0)
            if passed.sum() < 3 or ok.sum() < 30:
                continue
            x_all, y_all = traced.x_mm[sl], traced.y_mm[sl]
            w_all = density[sl]
            xr, yr = (
                float(_dot(w_all[passed], x_all[passed]) / w_all[passed].sum()),
                float(_dot(w_all[passed], y_all[passed]) / w_all[passed].sum()),
            )
            L, M, opl_q = sphere_coordinates(
                x_all, y_all, traced.direction[sl], traced.opl_mm[sl], (xr, yr), self._exit_pupil(k, b)
            )
            pmap = fit_pupil_map(L[ok], M[ok], u[sl][ok], v[sl][ok])
            step_l, step_m = np.ptp(L[ok]) / (n1 - 1), np.ptp(M[ok]) / (n1 - 1)
            l_box = (max(L[passed].min() - step_l, L[ok].min()), min(L[passed].max() + step_l, L[ok].max()))
            m_box = (max(M[passed].min() - step_m, M[ok].min()), min(M[passed].max() + step_m, M[ok].max()))
            uu, vv = u[sl], v[sl]
            du, dv = np.ptp(uu) / (n1 - 1), np.ptp(vv) / (n1 - 1)
            uv_box = (uu[passed].min() - du, uu[passed].max() + du, vv[passed].min() - dv, vv[passed].max() + dv)
            x, y = x_all[passed], y_all[passed]
            w = w_all[passed]
            wave = opl_q[passed]
            lam = self.bands.wavelength_nm[b] * 1e-6
            waves = _rms_waves(L[passed], M[passed], wave, w, lam)
            na = 0.5 * max(np.ptp(L[passed]), np.ptp(M[passed]), 1e-4)
            pairs.append(
                _Pair(
                    k,
                    b,
                    lam,
                    pmap,
                    l_box,
                    m_box,
                    uv_box,
                    (x.min(), x.max(), y.min(), y.max()),
                    na,
                    waves,
                    reference=(xr, yr),
                    power=float(w.sum() * du * dv),
                )
            )
        return self._drop_negligible_bands(pairs)

    @staticmethod
    def _drop_negligible_bands(pairs: list[_Pair]) -> list[_Pair]:
        """Leave out the bands that carry less than :data:`NEGLIGIBLE_BAND` of their lenslet's light
        (coarse estimate): the spectrum's far tails, which the filter and the film all but stop,
        would otherwise cost a full diffraction computation each for < 0.01 % of the focus."""
        total: dict[int, float] = {}
        for p in pairs:
            total[p.lenslet] = total.get(p.lenslet, 0.0) + p.power
        return [p for p in pairs if p.power >= NEGLIGIBLE_BAND * total[p.lenslet]]

    def _windows(self, pairs: list[_Pair]) -> dict[int, _Window]:
        """Each lenslet's window: the union of its bands' spots plus the diffraction margin,
        clipped to the frame, with the centres of its ``q``×``q`` sub-samples per pixel."""
        boxes: dict[int, list[float]] = {}
        for p in pairs:
            margin = self.settings.margin * p.wavelength_mm / (2 * p.na)
            box = [p.spot[0] - margin, p.spot[1] + margin, p.spot[2] - margin, p.spot[3] + margin]
            if p.lenslet in boxes:
                w = boxes[p.lenslet]
                box = [min(w[0], box[0]), max(w[1], box[1]), min(w[2], box[2]), max(w[3], box[3])]
            boxes[p.lenslet] = box
        rows, cols = self.grid.shape
        q = self._q
        offsets = ((np.arange(q) + 0.5) / q - 0.5) * self.grid.pitch_mm
        out = {}
        for k, (x0, x1, y0, y1) in boxes.items():
            c0 = max(int(math.floor(self.grid.col(x0))), 0)
            c1 = min(int(math.ceil(self.grid.col(x1))), cols - 1)
            r0 = max(int(math.floor(self.grid.row(y0))), 0)
            r1 = min(int(math.ceil(self.grid.row(y1))), rows - 1)
            if c1 >= c0 and r1 >= r0:
                xs = (self.grid.x_mm(np.arange(c0, c1 + 1))[:, None] + offsets[None, :]).ravel()
                ys = (self.grid.y_mm(np.arange(r0, r1 + 1))[:, None] + offsets[None, :]).ravel()
                out[k] = _Window(r0, r1, c0, c1, q, xs, ys)
        return out

    def _fine(self, source: np.ndarray, pairs: list[_Pair], windows: dict[int, _Window]) -> list[_Pair]:
        """Pass 2: uniform direction grids (diffraction) or uniform launch grids (geometric),
        traced together; fills each pair's pupil or splat. Returns the pairs that got light."""
        us, vs, ks, bs = [], [], [], []
        start = 0
        kept = []
        for p in pairs:
            window = windows.get(p.lenslet)
            if window is None:
                continue
            if p.geometric:
                n = self.settings.geometric_rays
                u0, u1, v0, v1 = p.uv_box
                uu, vv = np.meshgrid(np.linspace(u0, u1, n), np.linspace(v0, v1, n))
                u, v = uu.ravel(), vv.ravel()
                p.grid = (n, (u1 - u0) / (n - 1), (v1 - v0) / (n - 1))
            else:
                h = window.pitch_mm
                extent = max(p.l_box[1] - p.l_box[0], p.m_box[1] - p.m_box[0])
                n_fft, spacing = fft_size(max(len(window.xs), len(window.ys)), extent, h, p.wavelength_mm)
                n_l = int(math.ceil((p.l_box[1] - p.l_box[0]) / spacing)) + 1
                n_m = int(math.ceil((p.m_box[1] - p.m_box[0]) / spacing)) + 1
                l_axis = 0.5 * (p.l_box[0] + p.l_box[1]) + (np.arange(n_l) - (n_l - 1) / 2) * spacing
                m_axis = 0.5 * (p.m_box[0] + p.m_box[1]) + (np.arange(n_m) - (n_m - 1) / 2) * spacing
                uu, vv = p.pupil_map.grid(l_axis, m_axis)
                u, v = uu.ravel(), vv.ravel()
                p.grid = (l_axis, m_axis, spacing, n_fft, uu, vv)
            us.append(u)
            vs.append(v)
            ks.append(p.lenslet)
            bs.append(p.band)
            p.rays = slice(start, start + u.size)
            p.power = 0.0  # the coarse estimate gives way to the fine pass's
            start += u.size
            kept.append(p)
        if not kept:
            return []
        u, v = np.concatenate(us), np.concatenate(vs)
        group = np.repeat(np.arange(len(kept)), [len(a) for a in us])
        pair_band = np.array(bs)
        traced = trace_rays(self.optics, self._batch(source, u, v, np.array(ks), pair_band, group), self.engine)
        density = self._power_density(traced, u, v, pair_band[group])
        lit = []
        for p in kept:
            if p.geometric:
                self._finish_geometric(p, traced, density, windows[p.lenslet])
            else:
                self._finish_pupil(p, traced, density)
            if p.power > 0:
                lit.append(p)
        return lit

    def _finish_pupil(self, p: _Pair, traced: TracedRays, density: np.ndarray) -> None:
        l_axis, m_axis, spacing, _, uu, vv = p.grid
        sl = p.rays
        shape = (len(m_axis), len(l_axis))
        x_ref, y_ref = p.reference
        L, M, opl_q = sphere_coordinates(
            traced.x_mm[sl],
            traced.y_mm[sl],
            traced.direction[sl],
            traced.opl_mm[sl],
            p.reference,
            self._exit_pupil(p.lenslet, p.band),
        )
        L, M, opl_q = L.reshape(shape), M.reshape(shape), opl_q.reshape(shape)
        # |∂(u, v)/∂(L, M)| from the traced grid itself (index derivatives cancel).
        with np.errstate(invalid="ignore", divide="ignore"):
            uv = np.gradient(uu, axis=1) * np.gradient(vv, axis=0) - np.gradient(uu, axis=0) * np.gradient(vv, axis=1)
            lm = np.gradient(L, axis=1) * np.gradient(M, axis=0) - np.gradient(L, axis=0) * np.gradient(M, axis=1)
            jac = np.abs(uv / lm)
        w = density[sl].reshape(shape) * jac
        w = np.where(np.isfinite(w), w, 0.0)
        total = w.sum()
        if not total > 0:
            return
        x = np.nan_to_num(traced.x_mm[sl].reshape(shape))
        y = np.nan_to_num(traced.y_mm[sl].reshape(shape))
        wave = np.where(w > 0, opl_q, 0.0)
        wave = np.where(w > 0, wave - np.sum(w * wave) / total, 0.0)
        p.power = float(total * spacing * spacing)
        p.centroid = (float(np.sum(w * x) / total), float(np.sum(w * y) / total))
        p.pupil = Pupil(
            p.lenslet, p.band, p.wavelength_mm, l_axis, m_axis, spacing, np.sqrt(w), wave, x_ref, y_ref, p.power
        )

    def _exit_pupil(self, lenslet: int, band: int) -> np.ndarray:
        """Centre (x, y, z; mm) of a lenslet's paraxial exit pupil: its vertex (the stop) seen from
        the air above the sensor through the PMMA and the film; where the array or the sensor is
        tilted, turned with the array and given in the sensor's axes (as the traced rays)."""
        optics = self.optics
        cell = optics.lenslets[lenslet]
        depth = optics.flat_z_mm + self.design.mla.thickness_mm / self._indices[band, 1]
        if optics.film is not None:
            depth -= optics.film.thickness_mm * (1.0 - 1.0 / self._indices[band, 2])
        point = (cell.vertex_x_mm, cell.vertex_y_mm, depth)
        if optics.mla_tilt:
            point = rotate(optics.mla_tilt, *point, optics.mla_pivot_mm)
        if optics.sensor_tilt:
            point = rotate(optics.sensor_tilt, *point, inverse=True)
        return np.array(point, float)

    def _finish_geometric(self, p: _Pair, traced: TracedRays, density: np.ndarray, window: _Window) -> None:
        """Geometric branch: each cell of the launch grid is cut into s × s sub-cells (bilinear in
        the traced corners; s per cell, the smallest that makes its sub-cells ≤ 2 output samples
        across, at most 16), whose power is deposited on the nearest output sample and blurred by
        a Gaussian: the aperture's diffraction core or, if wider, 0.7 × the largest sub-cell
        (which smooths the lattice of deposits to < 10⁻⁴). Nearest-sample deposits widen that
        Gaussian by h²/12 in variance (< 2 %), less than bilinear ones would (h²/6)."""
        n, du, dv = p.grid
        sl = p.rays
        w = density[sl].reshape(n, n)
        ok = traced.traced[sl].reshape(n, n)
        x = traced.x_mm[sl].reshape(n, n)
        y = traced.y_mm[sl].reshape(n, n)
        c00, c01, c10, c11 = (
            (slice(0, -1), slice(0, -1)),
            (slice(0, -1), slice(1, None)),
            (slice(1, None), slice(0, -1)),
            (slice(1, None), slice(1, None)),
        )
        cell_ok = ok[c00] & ok[c01] & ok[c10] & ok[c11] & ((w[c00] + w[c01] + w[c10] + w[c11]) > 0)
        if not cell_ok.any():
            return
        corners_x = np.array([x[c][cell_ok] for c in (c00, c01, c10, c11)])  # (4, cells)
        corners_y = np.array([y[c][cell_ok] for c in (c00, c01, c10, c11)])
        corners_w = np.array([w[c][cell_ok] for c in (c00, c01, c10, c11)])
        h = window.pitch_mm
        footprint = np.maximum(np.ptp(corners_x, axis=0), np.ptp(corners_y, axis=0))  # per cell, mm
        sub = np.clip(np.ceil(footprint / (2 * h)), 1, 16).astype(int)
        px, py, pw = [], [], []
        for s in np.unique(sub):
            own = sub == s
            t = (np.arange(s) + 0.5) / s
            a, b = (g.ravel() for g in np.meshgrid(t, t))  # a along u (columns), b along v (rows)
            weights = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])  # (4, s²)
            px.append(np.einsum("kc,ks->cs", corners_x[:, own], weights).ravel())
            py.append(np.einsum("kc,ks->cs", corners_y[:, own], weights).ravel())
            pw.append(np.einsum("kc,ks->cs", corners_w[:, own], weights).ravel() * (du * dv / s**2))
        px, py, pw = np.concatenate(px), np.concatenate(py), np.concatenate(pw)
        p.power = float(pw.sum())
        if not p.power > 0:
            return
        p.centroid = (float(_dot(pw, px) / p.power), float(_dot(pw, py) / p.power))
        rows, cols = len(window.ys), len(window.xs)
        col = np.rint((px - window.xs[0]) / h).astype(np.intp)
        row = np.rint((py - window.ys[0]) / h).astype(np.intp)
        keep = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
        splat = np.bincount(row[keep] * cols + col[keep], pw[keep], minlength=rows * cols).reshape(rows, cols)
        sigma = max(0.42 * p.wavelength_mm / (2 * p.na), 0.7 * float(np.max(footprint / sub))) / h
        p.splat = gaussian_filter(splat, sigma, mode="constant")

    @staticmethod
    def _merge_geometric(pairs: list[_Pair], threshold: float, mid_band: int, wavelength_mm: float) -> list[_Pair]:
        """One geometric record (all bands at once) for every lenslet whose rays' RMS wavefront
        error exceeds ``threshold`` waves in any band; the other lenslets keep their bands."""
        out, by_lenslet = [], {}
        for p in pairs:
            by_lenslet.setdefault(p.lenslet, []).append(p)
        for k, own in by_lenslet.items():
            if max(p.waves for p in own) <= threshold:
                out += own
                continue
            boxes = np.array([p.uv_box for p in own])
            spots = np.array([p.spot for p in own])
            out.append(
                _Pair(
                    k,
                    -1,
                    wavelength_mm,
                    own[0].pupil_map,
                    own[0].l_box,
                    own[0].m_box,
                    (boxes[:, 0].min(), boxes[:, 1].max(), boxes[:, 2].min(), boxes[:, 3].max()),
                    (spots[:, 0].min(), spots[:, 1].max(), spots[:, 2].min(), spots[:, 3].max()),
                    max(p.na for p in own),
                    max(p.waves for p in own),
                    geometric=True,
                )
            )
        return out

    def _prepare(self, position_mm, lenslets=None, bands=None, force_diffraction: bool = False):
        source = self.device_point_mm(position_mm)
        lenslets = self._visible if lenslets is None else list(lenslets)
        bands = list(range(len(self.bands))) if bands is None else list(bands)
        pairs = self._coarse(source, lenslets, bands)
        windows = self._windows(pairs)
        if not force_diffraction:
            lam = self.bands.wavelength_nm[self._mid_band] * 1e-6
            pairs = self._merge_geometric(pairs, self.settings.geometric_waves, self._mid_band, lam)
        return self._fine(source, pairs, windows), windows

    # -- public --------------------------------------------------------------------------------
    def pupils(
        self,
        position_mm: tuple[float, float, float] | np.ndarray,
        lenslets: list[int] | None = None,
        bands: list[int] | None = None,
    ) -> list[Pupil]:
        """The sampled pupils (diffraction branch, forced) of a source at ``position_mm`` (object
        space, mm) for the given lenslets and bands (default: all visible lenslets, all bands);
        lenslets that get no light are left out."""
        pairs, _ = self._prepare(position_mm, lenslets, bands, force_diffraction=True)
        return [p.pupil for p in pairs if p.pupil is not None]

    def foci(
        self,
        position_mm: tuple[float, float, float] | np.ndarray,
        aberration_free: bool = False,
        lenslets: list[int] | None = None,
        diameter_um: float | None = None,
        bands: list[int] | None = None,
    ) -> list[Focus]:
        """The foci of a source at ``position_mm`` (object space: x, y from the central lenslet's
        axis, z from the nominal focal plane, +z towards the device; mm), one per lenslet that
        sends light onto the sensor. ``aberration_free`` drops the wavefront and forces the
        diffraction branch (tests: the same apertures, diffraction-limited). ``diameter_um``
        (µm) overrides the source's diameter (emitters of several sizes, one model). ``lenslets``
        and ``bands`` (indices) restrict the computation (default: all)."""
        pairs, windows = self._prepare(position_mm, lenslets, bands, force_diffraction=aberration_free)
        diameter = self.source.diameter_um if diameter_um is None else float(diameter_um)
        if not (math.isfinite(diameter) and 0 <= diameter <= 200):
            raise ValueError(f"diameter_um = {diameter_um!r}: must lie within 0–200 µm")
        kernel = None
        if diameter > 0:  # the source's image: its diameter × the chief-ray magnification at its depth
            m = first_order.chief_ray_magnification(self.design, float(self.device_point_mm(position_mm)[2]))
            kernel = disc_kernel(m * diameter / 1000.0, self.grid.pitch_mm / self._q)
        foci = []
        for k, window in windows.items():
            own = [p for p in pairs if p.lenslet == k]
            if not own:
                continue
            fine = np.zeros((len(window.ys), len(window.xs)))
            h = window.pitch_mm
            for p in own:
                if p.geometric:
                    fine += p.splat
                    continue
                pupil = p.pupil
                _, _, spacing, n_fft, _, _ = p.grid
                fine += debye_fft(
                    pupil.field(aberration_free),
                    spacing,
                    pupil.wavelength_mm,
                    n_fft,
                    window.xs[0] - pupil.x_ref_mm,
                    window.ys[0] - pupil.y_ref_mm,
                    fine.shape,
                ) * (h * h)
            if kernel is not None:
                fine = fftconvolve(fine, kernel, mode="same")
            q = window.q
            patch = fine.reshape(window.r1 - window.r0 + 1, q, window.c1 - window.c0 + 1, q).sum(axis=(1, 3))
            epsf = None
            if self.settings.oversample > 1:
                from cm2optics.emission.epsf import epsf_from_subsamples

                epsf = np.clip(epsf_from_subsamples(fine, q, self.settings.oversample), 0.0, None).astype(np.float32)
            power = sum(p.power for p in own)
            cx = sum(p.power * p.centroid[0] for p in own) / power
            cy = sum(p.power * p.centroid[1] for p in own) / power
            t = self.optics.lenslets[k].transmission  # as built (dust, a defect): 1 by design
            foci.append(
                Focus(
                    k,
                    window.r0,
                    window.c0,
                    t * np.clip(patch, 0.0, None),
                    (cx, cy),
                    t * power,
                    any(p.geometric for p in own),
                    None if epsf is None else t * epsf,
                )
            )
        return foci

    def image(self, position_mm: tuple[float, float, float] | np.ndarray) -> np.ndarray:
        """The full (binned) frame of a source at ``position_mm``: photons detected per photon
        emitted, per pixel, float64 of shape :attr:`SensorGrid.shape`."""
        frame = np.zeros(self.grid.shape)
        for focus in self.foci(position_mm):
            add_focus(frame, focus)
        return frame


def add_focus(frame: np.ndarray, focus: Focus, scale: float = 1.0) -> None:
    """Add ``scale`` × a focus's patch into ``frame`` (in place)."""
    h, w = focus.patch.shape
    frame[focus.row0 : focus.row0 + h, focus.col0 : focus.col0 + w] += scale * focus.patch
