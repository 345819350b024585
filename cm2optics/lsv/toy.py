"""Toy CM²-like forward models for tests, demos and fast fall-backs: not physics.

The physical simulation is :mod:`cm2optics.emission`; these models are quick, closed-form
stand-ins whose truth is known, so that the LSV tools, the synthesiser and the solvers can be
built and tested without a ray tracer:

- :class:`AnalyticCM2`: nine anisotropic Gaussian foci per point source placed by paraxial
  chief-ray geometry (below), and :func:`write_analytic_scan`, a synthetic PSF scan of it;
- :func:`analytic_lsv_model`: an in-memory LSV model of it, straight from noise-free crops;
- :func:`analytic_lsv_model_file`: an LSV model file of it, built (once) the way a user does,
  from a synthetic scan through ``cm2 lsv build``'s :func:`~cm2optics.lsv.build.build_model`;
- :func:`gaussian_lsi_operator`: a tiny depth-wise LSI operator with isotropic Gaussian foci
  (no LSV model at all), for the solver and synthesiser tests.

For a source at object position (x, y, z) (mm; z from the nominal focal plane, +z towards the
device) and a lenslet whose vertex sits at c (mm, device frame), the chief ray through the
vertex lands on the sensor at ``s = c − m(z)·((x, y) − c)`` (mm from the sensor centre): the
image through each lenslet is inverted. ``m(z) = m₀·D/(D − z)`` with ``m₀`` the design's
magnification and ``D`` the reduced distance from the focal plane to the lenslet vertices
(working distance less the emission filter's ``t·(1 − 1/n)``), so that the off-axis foci shear
laterally with depth as in the paper. Each focus is a Gaussian whose width grows with defocus
from its lenslet's best focus (``σ_def = ½·NA·|z − κ·ρ²|·m``, κ the field curvature, 0 by
default) and, along the direction away from its lenslet's axis, with the off-axis distance
``ρ`` (``×(1 + a·ρ²)``); it is pushed outwards by a radial distortion
``b·ρ³`` and dimmed by a soft vignetting edge at ``ρ_v`` (side foci vanish for sources far
from a lenslet, as in the paper for lateral positions > 1.7 mm). A source of diameter ``d``
(``source_diameter_um``, a uniform disc) blurs each focus by its image, a disc ``d·m`` across
(m the focus's own magnification at the source's depth), whose second moment ``(d·m)²/16`` per
axis is added to the Gaussian's covariance (the equal-moment Gaussian of the disc's convolution).
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.design.materials import refractive_index
from cm2optics.formats.scan import ScanMeta, write_scan
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.lsi import DepthwiseConvOperator
from cm2optics.optics import first_order
from cm2optics.optics.tilt import tilt_matrix

__all__ = [
    "AnalyticCM2",
    "analytic_crops",
    "analytic_geometry",
    "analytic_lsv_model",
    "analytic_lsv_model_file",
    "analytic_scan_images",
    "gaussian_lsi_operator",
    "write_analytic_scan",
]


@dataclass(frozen=True)
class AnalyticCM2:
    """The analytic model's parameters (lengths as named).

    magnification: m₀ at the focal plane.
    reduced_distance_mm: D, focal plane to the lenslet vertices in reduced (air) units, mm.
    lenslet_centres_mm: (J, 2) lenslet vertices (x, y) in the device frame, mm.
    rows, cols: lenslet layout (J = rows·cols, row by row).
    pixel_um: image pixel pitch (after binning), µm. binning: sensor pixels per image pixel and axis.
    axial_step_um: axial voxel pitch of the model's default reconstruction grid, µm.
    shape: image shape (y, x), pixels.
    object_na: object-side NA of one lenslet (sets the defocus blur).
    sigma0_um: in-focus Gaussian σ of a focus on the sensor, µm (None: one sensor pixel).
    aberration_per_mm2: a, radial widening per mm² of off-axis distance.
    distortion_um_per_mm3: b, radial displacement of a focus on the sensor per mm³, µm.
    vignetting_mm: ρ_v, off-axis distance where a focus is half as bright, mm.
    vignetting_soft_mm: width of the vignetting edge, mm.
    offset_px: (row, col) displacement of the whole image on the sensor, px (a sensor placed off
        its nominal position).
    field_curvature_per_mm: κ, lenslet j's best focus lies at ``z = κ·ρ²`` (mm, ρ its off-axis
        distance in mm): the defocus blur grows with ``|z − κ·ρ²|`` (0: a flat focal plane).
    lenslet_magnification: (J,) factor on m(z) per lenslet (empty: all 1), e.g. a lenslet moved
        along the axis by a tilted array.
    lenslet_focus_mm: (J,) extra object-space z of each lenslet's best focus, mm (empty: all 0).
    source_diameter_um: d, the diameter of the source (a uniform disc), µm in object space (0: a
        point): each focus's covariance gains (d·m/pixel)²/16 px² per axis, m its magnification.
    sensor_tilt_deg: (θx, θy) the sensor tilted right-handedly about x, then y, about its centre,
        degrees: at (x, y) it sits ``h = y·sin θx − x·sin θy`` higher (towards the lenslets), so
        each focus meets it early along its chief ray (from the vertex, ``m₀·D`` above the sensor:
        the paraxial image distance) and is defocused by ``h/m²`` in object space; its position is
        read in the sensor's own (tilted) axes.
    """

    magnification: float
    reduced_distance_mm: float
    lenslet_centres_mm: tuple[tuple[float, float], ...]
    rows: int
    cols: int
    pixel_um: float
    shape: tuple[int, int]
    binning: int
    axial_step_um: float
    object_na: float = 0.053
    sigma0_um: float | None = None
    aberration_per_mm2: float = 0.12
    distortion_um_per_mm3: float = 0.3
    vignetting_mm: float = 3.2
    vignetting_soft_mm: float = 0.25
    offset_px: tuple[float, float] = (0.0, 0.0)
    field_curvature_per_mm: float = 0.0
    lenslet_magnification: tuple[float, ...] = ()
    lenslet_focus_mm: tuple[float, ...] = ()
    sensor_tilt_deg: tuple[float, float] = (0.0, 0.0)
    source_diameter_um: float = 0.0

    def __post_init__(self) -> None:
        if self.sigma0_um is None:
            object.__setattr__(self, "sigma0_um", self.pixel_um / self.binning)

    @classmethod
    def from_design(cls, design: SystemDesign, binning: int = 1, **changes: float) -> AnalyticCM2:
        """The model of ``design`` on its sensor, binned ``binning``×; ``changes`` override fields."""
        n_filter = refractive_index(design.emission_filter.material, design.imaging.design_wavelength_nm)
        reduced = first_order.working_distance_mm(design) - design.emission_filter.thickness_mm * (1.0 - 1.0 / n_filter)
        model = cls(
            magnification=first_order.magnification(design),
            reduced_distance_mm=reduced,
            lenslet_centres_mm=tuple(tuple(c) for c in design.mla.lenslet_centres_mm()),
            rows=design.mla.rows,
            cols=design.mla.cols,
            pixel_um=design.sensor.pixel_um * binning,
            shape=(design.sensor.height_px // binning, design.sensor.width_px // binning),
            binning=binning,
            axial_step_um=design.volume.axial_step_um,
            object_na=first_order.object_na(design),
        )
        return replace(model, **changes) if changes else model

    def magnification_at(self, z_mm: float | np.ndarray) -> np.ndarray:
        """m(z) = m₀·D/(D − z)."""
        return self.magnification * self.reduced_distance_mm / (self.reduced_distance_mm - np.asarray(z_mm, float))

    def foci(self, x_mm: float, y_mm: float, z_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centres (J, 2) as (row, col) pixels, covariances (J, 2, 2) in pixels², and fluxes (J,)
        (sum over the image of each focus) of a unit point source."""
        c = np.asarray(self.lenslet_centres_mm, float)
        m = float(self.magnification_at(z_mm)) * (
            np.asarray(self.lenslet_magnification) if self.lenslet_magnification else np.ones(len(c))
        )
        rel = np.array([x_mm, y_mm]) - c  # source relative to each lenslet axis, mm
        rho = np.hypot(rel[:, 0], rel[:, 1])
        s_mm = c - m[:, None] * rel
        direction = -rel / np.maximum(rho, 1e-9)[:, None]  # on the sensor the image is inverted
        s_mm = s_mm + direction * (self.distortion_um_per_mm3 * rho**3 / 1000.0)[:, None]
        defocus_mm = z_mm - self.field_curvature_per_mm * rho**2  # from each lenslet's best focus
        if self.lenslet_focus_mm:
            defocus_mm = defocus_mm - np.asarray(self.lenslet_focus_mm, float)
        if self.sensor_tilt_deg != (0.0, 0.0):
            s_mm, defocus_mm = self._on_tilted_sensor(c, s_mm, m, defocus_mm)
        row = (self.shape[0] - 1) / 2.0 + self.offset_px[0] + s_mm[:, 1] * 1000.0 / self.pixel_um
        col = (self.shape[1] - 1) / 2.0 + self.offset_px[1] + s_mm[:, 0] * 1000.0 / self.pixel_um
        sigma_um = np.hypot(self.sigma0_um, 0.5 * self.object_na * np.abs(defocus_mm) * 1000.0 * m)
        sigma_t = sigma_um / self.pixel_um
        sigma_r = sigma_t * (1.0 + self.aberration_per_mm2 * rho**2)
        cov = np.empty((len(c), 2, 2))
        for j in range(len(c)):
            u = np.array([direction[j, 1], direction[j, 0]])  # (row, col) radial unit vector
            if rho[j] < 1e-9:
                u = np.array([1.0, 0.0])
            v = np.array([-u[1], u[0]])
            cov[j] = sigma_r[j] ** 2 * np.outer(u, u) + sigma_t[j] ** 2 * np.outer(v, v)
        if self.source_diameter_um > 0:  # the source's disc image, d·m across: its second moment per axis
            disc_px = self.source_diameter_um * m / self.pixel_um
            cov = cov + (disc_px**2 / 16.0)[:, None, None] * np.eye(2)
        cos4 = (self.reduced_distance_mm / np.hypot(self.reduced_distance_mm, rho)) ** 4
        vignetting = 1.0 / (1.0 + np.exp((rho - self.vignetting_mm) / self.vignetting_soft_mm))
        flux = cos4 * vignetting * (self.reduced_distance_mm / (self.reduced_distance_mm - z_mm)) ** 2
        return np.stack([row, col], axis=1), cov, flux

    def _on_tilted_sensor(
        self, vertices: np.ndarray, s_mm: np.ndarray, m: np.ndarray, defocus_mm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Foci ``s_mm`` (J, 2) on the flat sensor moved onto the tilted one (class docstring):
        where each chief ray, from its vertex ``m₀·D`` above the sensor, meets the tilted plane,
        in the plane's own axes (mm), and the defocus (mm, object space) grown by h/m²."""
        r = tilt_matrix(*self.sensor_tilt_deg)
        normal = r[:, 2]
        image_distance = self.magnification * self.reduced_distance_mm
        slope = (s_mm - vertices) / image_distance  # lateral mm per mm of descent along the chief ray
        # the plane n·p = 0 met at height h on the ray p = (s − h·slope, h): n·(s − h·slope) + n_z·h = 0
        h = -(s_mm @ normal[:2]) / (normal[2] - slope @ normal[:2])
        hit = np.column_stack([s_mm - h[:, None] * slope, h])
        local = hit @ r[:, :2]  # coordinates along the tilted sensor's own x and y axes
        return local, defocus_mm + h / m**2

    def focus_window(
        self, x_mm: float, y_mm: float, z_mm: float, j: int, centre: np.ndarray, shape: tuple[int, int]
    ) -> np.ndarray:
        """Focus ``j`` of a unit source sampled on a ``shape`` window whose pixel (h//2, w//2) sits
        at ``centre`` (row, col) px of the image."""
        centres, covs, fluxes = self.foci(x_mm, y_mm, z_mm)
        out = np.zeros(shape)
        offset = centres[j] - np.asarray(centre, float) + np.array([shape[0] // 2, shape[1] // 2])
        _add_gaussian(out, offset, covs[j], fluxes[j])
        return out

    def image(
        self,
        x_mm: float,
        y_mm: float,
        z_mm: float,
        *,
        lenslets: np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> np.ndarray:
        """The image (y, x) of a unit point source, float64, each focus integrated over its pixels
        (3×3 sub-samples per pixel); ``lenslets`` restricts it to some foci, ``weights`` (J,)
        scales each focus's flux (transmission, source profile)."""
        out = np.zeros(self.shape)
        centres, covs, fluxes = self.foci(x_mm, y_mm, z_mm)
        if weights is not None:
            fluxes = fluxes * np.asarray(weights, float)
        for j in range(len(centres)) if lenslets is None else lenslets:
            _add_gaussian(out, centres[j], covs[j], fluxes[j])
        return out


def analytic_geometry(model: AnalyticCM2, z_mm: np.ndarray, degree: int = 2):
    """The paraxial geometry of ``model`` (no distortion) fitted as polynomials over ``z_mm``."""
    from cm2optics.lsv.preprocess import Geometry, _polyfit

    z = np.asarray(z_mm, float)
    m = model.magnification_at(z) * 1000.0 / model.pixel_um  # px per mm
    centre = np.array([(model.shape[0] - 1) / 2.0, (model.shape[1] - 1) / 2.0])
    c = np.asarray(model.lenslet_centres_mm, float)[:, ::-1]  # (row ← y, col ← x), mm
    offsets = (c[None] * (1000.0 / model.pixel_um)) * (1.0 + model.magnification_at(z))[:, None, None]
    r_ref = offsets.mean(axis=1)
    A = np.zeros((len(z), 2, 2))
    A[:, 0, 1] = -m
    A[:, 1, 0] = -m
    return Geometry(
        r0_poly=_polyfit(z, centre[None] + r_ref, degree),
        A_poly=_polyfit(z, A, degree),
        o_poly=_polyfit(z, offsets - r_ref[:, None], degree),
        rows=model.rows,
        cols=model.cols,
    )


def analytic_crops(model: AnalyticCM2, geometry, positions_mm: np.ndarray, patch: tuple[int, int]) -> np.ndarray:
    """(N, J, h, w) noise-free crops of the model's foci around ``geometry``'s predicted chief rays."""
    positions_mm = np.asarray(positions_mm, float)
    J = model.rows * model.cols
    out = np.zeros((len(positions_mm), J) + tuple(patch), np.float32)
    for n, (x, y, z) in enumerate(positions_mm):
        centres = geometry.focus(x, y, z)
        for j in range(J):
            out[n, j] = model.focus_window(x, y, z, j, centres[j], patch)
    return out


def analytic_lsv_model(
    model: AnalyticCM2,
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    z_mm: np.ndarray,
    *,
    rank: int = 64,
    patch_px: int | None = None,
    axial_um: float | None = None,
    trim: float | None = 1e-6,
    focal_surface: bool = False,
    refine: int = 2,
    per_lenslet: bool = False,
):
    """An :class:`~cm2optics.lsv.model.LSVModel` of the analytic system built straight from
    noise-free crops on the grid x × y × z (mm): no scan files, the paraxial geometry known.
    ``focal_surface``: estimate each lenslet's best-focus surface from the crops and interpolate
    along it on the grid refined ``refine`` times (:mod:`cm2optics.lsv.focal_surface`). ``per_lenslet``:
    each lenslet its own ``rank``-term basis (:func:`~cm2optics.lsv.decompose.decompose_per_lenslet`)."""
    from cm2optics.lsv.build import default_patch_px, model_from_crops
    from cm2optics.lsv.focal_surface import estimate_focal_surface

    patch = patch_px or default_patch_px(model.binning)
    xs, ys, zs = (np.asarray(a, float) for a in (x_mm, y_mm, z_mm))
    geometry = analytic_geometry(model, zs)
    positions = np.array([[x, y, z] for z in zs for y in ys for x in xs])
    grid_index = np.array([[ix, iy, iz] for iz in range(len(zs)) for iy in range(len(ys)) for ix in range(len(xs))])
    crops = analytic_crops(model, geometry, positions, (patch, patch))
    lsv, _ = model_from_crops(
        crops,
        grid_index,
        (xs, ys, zs),
        geometry,
        rank=rank,
        sensor_shape=model.shape,
        pixel_um=model.pixel_um,
        axial_um=model.axial_step_um if axial_um is None else axial_um,
        trim=trim,
        provenance={"source": "analytic CM²-like model (cm2optics.lsv.toy), noise-free crops"},
        focal_surface=estimate_focal_surface(crops, grid_index, (xs, ys, zs)) if focal_surface else None,
        refine=refine,
        per_lenslet=per_lenslet,
    )
    return lsv


def _add_gaussian(out: np.ndarray, centre: np.ndarray, cov: np.ndarray, flux: float) -> None:
    if flux <= 1e-12:
        return
    half = int(math.ceil(5.0 * math.sqrt(max(np.linalg.eigvalsh(cov))))) + 2
    r0, c0 = int(round(centre[0])), int(round(centre[1]))
    rs = slice(max(r0 - half, 0), min(r0 + half + 1, out.shape[0]))
    cs = slice(max(c0 - half, 0), min(c0 + half + 1, out.shape[1]))
    if rs.start >= rs.stop or cs.start >= cs.stop:
        return
    sub = (np.arange(3) - 1) / 3.0
    rr = np.arange(rs.start, rs.stop)[:, None, None, None] + sub[None, None, :, None] - centre[0]
    cc = np.arange(cs.start, cs.stop)[None, :, None, None] + sub[None, None, None, :] - centre[1]
    inv = np.linalg.inv(cov)
    q = inv[0, 0] * rr**2 + 2 * inv[0, 1] * rr * cc + inv[1, 1] * cc**2
    density = np.exp(-0.5 * q).mean(axis=(2, 3)) / (2 * math.pi * math.sqrt(np.linalg.det(cov)))
    out[rs, cs] += flux * density


def analytic_scan_images(
    model: AnalyticCM2,
    positions_mm: np.ndarray,
    *,
    peak_counts: float = 3000.0,
    dark_level: float = 100.0,
    background_per_ms: float = 0.5,
    bit_depth: int = 12,
    noise: bool = True,
    read_noise_counts: float = 2.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """uint16 images (N, y, x) and exposures (N,) ms of point sources at ``positions_mm``.

    Like a lab scan: the exposure adapts so that the brightest pixel reaches about
    ``peak_counts`` (a source delivers 1000 flux units per ms); a uniform background of
    ``background_per_ms`` counts/ms and the dark level are added; with ``noise``, Poisson
    photon noise and Gaussian read noise (``read_noise_counts``) follow (seeded).
    """
    rng = np.random.default_rng(seed)
    images, exposures = [], []
    full = 2**bit_depth - 1
    for x, y, z in np.asarray(positions_mm, float):
        rate = model.image(x, y, z) * 1000.0  # counts per ms
        peak = float(rate.max()) + background_per_ms
        exposure = max(round(peak_counts / peak, 2), 0.01) if peak > 0 else 1.0
        signal = (rate + background_per_ms) * exposure
        if noise:
            signal = rng.poisson(signal).astype(float) + rng.normal(0.0, read_noise_counts, signal.shape)
        counts = np.clip(np.round(signal + dark_level), 0, full).astype(np.uint16)
        images.append(counts)
        exposures.append(exposure)
    return np.stack(images), np.asarray(exposures)


def write_analytic_scan(
    folder: str | Path,
    model: AnalyticCM2,
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    z_mm: np.ndarray,
    *,
    binning: int = 1,
    dark_level: float = 100.0,
    bit_depth: int = 12,
    **options: float,
) -> Path:
    """Write a scan folder of the analytic model over the grid x × y × z (mm), in the shared
    PSF-scan format (:mod:`cm2optics.formats.scan`); ``options`` go to :func:`analytic_scan_images`."""
    positions = np.array([[x, y, z] for z in z_mm for y in y_mm for x in x_mm], float)
    images, exposures = analytic_scan_images(model, positions, dark_level=dark_level, bit_depth=bit_depth, **options)
    meta = ScanMeta(
        pixel_um=model.pixel_um,
        binning=binning,
        bit_depth=bit_depth,
        dark_level=dark_level,
        extra={"lenslets": [model.rows, model.cols], "source": "analytic CM²-like model (cm2optics.lsv.toy)"},
    )
    return write_scan(folder, images, positions, exposures, meta)


def analytic_lsv_model_file(
    path: str | Path, design: Any, *, binning: int = 4, rank: int = 8, lateral_nodes: int = 7, depth_nodes: int = 5
) -> Path:
    """Build (once) an LSV model of ``design`` from a synthetic PSF scan of the analytic CM²-like
    PSF (:class:`AnalyticCM2`) on a ``lateral_nodes``² × ``depth_nodes`` grid over
    ±3.6 mm × ±0.4 mm, binned ``binning``×; returns its path (reused if it exists). Keep the
    lateral step ≤ 1.2 mm (7 nodes): at 1.8 mm the foci move further than the geometry fit's
    lattice search expects and the magnification comes out wrong."""
    from cm2optics.lsv.build import build_model

    path = Path(path)
    if path.is_file():
        return path
    scan = path.with_name(path.stem + "-scan")
    xs = np.linspace(-3.6, 3.6, lateral_nodes)
    write_analytic_scan(
        scan,
        AnalyticCM2.from_design(design, binning=binning),
        xs,
        xs,
        np.linspace(-0.4, 0.4, depth_nodes),
        binning=binning,
    )
    model = build_model(scan, rank=rank, design=design).model
    shutil.rmtree(scan, ignore_errors=True)
    return model.save(path)


def gaussian_lsi_operator(
    grid: VolumeGrid,
    sensor_shape: tuple[int, int],
    *,
    rows: int = 3,
    cols: int = 3,
    pitch_px: float | None = None,
    sigma0_px: float = 0.8,
    defocus_px_per_um: float = 0.012,
    shear_per_um: float = 2.5e-4,
    patch_px: int | None = None,
) -> DepthwiseConvOperator:
    """A small CM²-like depth-wise LSI operator with Gaussian foci, for tests and demos.

    rows × cols lenslets at ``pitch_px`` on the sensor (default: a third of the smaller sensor
    side); a focus widens with defocus (σ² = σ0² + (defocus·z)², px) and lenslet j's focus moves
    radially by ``shear_per_um·z`` × its offset (the axial shear that encodes depth); each focus
    carries 1/J of the light. The image is inverted (a source moved +x lands −x).
    """
    H, W = sensor_shape
    nz, ny, nx = grid.shape
    pitch = float(pitch_px) if pitch_px is not None else min(H, W) / 3.0
    z_um = grid.axis_um(0)
    sigma = np.sqrt(sigma0_px**2 + (defocus_px_per_um * z_um) ** 2)
    half = int(math.ceil(4 * sigma.max())) + 1
    size = patch_px if patch_px is not None else 2 * half + 1
    J = rows * cols
    offsets = np.array(
        [((r - (rows - 1) / 2) * pitch, (c - (cols - 1) / 2) * pitch) for r in range(rows) for c in range(cols)]
    )
    centre = np.array([(H - 1) / 2.0, (W - 1) / 2.0])
    patches = np.zeros((J, nz, size, size), np.float32)
    origins = np.zeros((J, nz, 2), np.int64)
    rays = centre + offsets
    plane_half = np.array([(ny - 1) / 2.0, (nx - 1) / 2.0])
    grid_px = np.arange(size)
    for j in range(J):
        for z in range(nz):
            focus = centre + offsets[j] * (1.0 + shear_per_um * z_um[z])  # source at the plane centre
            top_left_focus = focus - plane_half  # where the flipped plane's voxel (0, 0) focuses
            origin = np.floor(top_left_focus).astype(np.int64) - size // 2
            frac = top_left_focus - origin
            g_r = np.exp(-0.5 * ((grid_px - frac[0]) / sigma[z]) ** 2)
            g_c = np.exp(-0.5 * ((grid_px - frac[1]) / sigma[z]) ** 2)
            patch = np.outer(g_r, g_c)
            patches[j, z] = patch / patch.sum() / J
            origins[j, z] = origin
    meta = {
        "kind": "gaussian-cm2",
        "rows": rows,
        "cols": cols,
        "pitch_px": pitch,
        "sigma0_px": sigma0_px,
        "defocus_px_per_um": defocus_px_per_um,
        "shear_per_um": shear_per_um,
    }
    return DepthwiseConvOperator(patches, origins, grid, sensor_shape, (True, True), rays, meta=meta)
