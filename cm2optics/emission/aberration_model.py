"""The nodal-aberration model of each lenslet's PSF (its PSFs can make a 3D-LSV model's low-rank basis).

A basis made from the calibration nodes' crops cannot express the PSF's shape between the nodes
(aberrations and vignetting change faster than a linear blend of neighbours follows). This model
predicts a lenslet's PSF at any source position (x, y, z) mm from four fitted parts:

* **pupil coordinate** p = ((L, M) − (L0, M0)) / :data:`PUPIL_UNIT`, (L0, M0) the direction of the
  lenslet's exit-pupil centre seen from the reference point: tied to the lens aperture, whatever
  part of it passes;
* **wavefront** W(p; h, z) = Σ c (p·p)^a (h·p)^b (h·h)^c z^e (waves; 2a + b ≤ 4 without piston and
  tilt, c ≤ 2, e ≤ 2; h = (x, y) − the lenslet's axis, mm): the nodal aberration theory's terms,
  fitted to traced pupils with each node's piston and tilt free (:func:`fit_wavefront`);
* **passed region**: the intersection of 8 half-planes d_k·p ≤ e_k (d_k every 45°); each extent
  e_k(x, y, z) = min(a smooth 'cell' polynomial, up to two 'clip' pieces linear in x, y, z): the
  lens's own edge and the housing's bores vignetting it (:func:`fit_aperture`);
* **position and flux**: from the scan's crops, not from the design: the offset of each crop's
  bright core (its part above :data:`CORE_LEVEL` of its peak) from the render's and the log of
  their flux ratio, cubic polynomials in (x, y, z) fitted with trimming (:func:`fit_placement`).

The PSF is the Debye sum (:func:`~cm2optics.emission.wavefront.mft`) of a uniform-amplitude pupil
with that wavefront over that region, on the crops' fine grid, integrated over one pixel.
One band (the design's middle one), no source diameter: the model's PSFs are the basis' raw
material, their node coefficients are refitted to the scan by the low-rank build.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import convolve1d
from scipy.optimize import minimize

from cm2optics.emission.wavefront import mft

__all__ = [
    "CORE_LEVEL",
    "DIRECTIONS",
    "FIELD_DEGREE",
    "PUPIL_TERMS",
    "PUPIL_UNIT",
    "Aperture",
    "LensletModel",
    "NodalWavefront",
    "PupilSamples",
    "core_centroid",
    "fit_aperture",
    "fit_lenslet_model",
    "fit_placement",
    "fit_wavefront",
    "nodal_terms",
    "pixel_integrate",
    "placement_features",
    "pupil_extents",
    "trace_pupils",
]

#: Direction cosine per pupil unit (the unclipped aperture of a CM² V2 lenslet spans ≈ ±0.97 units).
PUPIL_UNIT = 0.1
#: Unit normals of the 8 half-planes bounding the passed region, every 45° from +x.
DIRECTIONS = np.array([[np.cos(t), np.sin(t)] for t in np.arange(8) * np.pi / 4])
#: Share of a PSF's peak above which its 'core' lies (the centroid that places it).
CORE_LEVEL = 0.2
#: Pupil samples per unit in the render (at least), and its half-width (units).
RENDER_SAMPLES_PER_UNIT = 60
RENDER_HALF_WIDTH = 1.25
#: The render's period λ/ΔL over its window, at least: an aberrated PSF's far side must not wrap
#: into the window (on the 9×9×11 binning-2 scan 1.1 → 1.75 took the held-out node error from
#: 0.072 to 0.067, the central lenslet's from 0.085 to 0.067; BENCHMARKS.md).
PERIOD_MARGIN = 1.75
#: Largest image-plane sample of the render's Debye sum, mm (the diffraction core is ≈ 2.5 µm wide).
MAX_SUBSAMPLE_MM = 1.25e-3
#: Pupil powers (a, b) of the wavefront's terms (p·p)^a (h·p)^b: 2a + b ≤ 4 without piston and tilt.
PUPIL_TERMS = tuple((a, b) for a in range(3) for b in range(5) if 2 * a + b <= 4 and not (a == 0 and b <= 1))
#: Highest power c of (h·h)^c in the wavefront's terms.
FIELD_DEGREE = 2
#: Pupil samples per node that enter the wavefront fit at most.
FIT_SAMPLES_PER_NODE = 1000

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class PupilSamples:
    """One traced pupil of one lenslet: source ``position_mm`` (x, y, z), passed samples at
    aperture-referenced coordinates ``p`` (n, 2) (pupil units), ``wavefront_waves`` (n,),
    ``amplitude`` (n,), the grid ``spacing`` (pupil units) and ``wavelength_mm``; ``extents``
    (8,): those of the whole passed region where ``p`` is a subsample of it (default: of ``p``)."""

    position_mm: tuple[float, float, float]
    p: np.ndarray
    wavefront_waves: np.ndarray
    amplitude: np.ndarray
    spacing: float
    wavelength_mm: float
    extents: np.ndarray | None = None

    def passed_extents(self) -> np.ndarray:
        """(8,) extents of the passed region along :data:`DIRECTIONS` (:func:`pupil_extents`)."""
        return self.extents if self.extents is not None else pupil_extents(self.p, self.spacing)


def nodal_terms(p: np.ndarray, h: np.ndarray, z: float | np.ndarray, depth_degree: int = 2) -> np.ndarray:
    """(n, T) terms (p·p)^a (h·p)^b (h·h)^c z^e for (a, b) in :data:`PUPIL_TERMS`, c ≤
    :data:`FIELD_DEGREE`, e ≤ ``depth_degree`` (in that order); p (n, 2), h (2,) or (n, 2) mm."""
    p = np.asarray(p, float)
    h = np.broadcast_to(np.asarray(h, float), p.shape)
    p2, hp, h2 = (p * p).sum(-1), (h * p).sum(-1), (h * h).sum(-1)
    z = np.broadcast_to(np.asarray(z, float), p2.shape)
    columns = [
        p2**a * hp**b * h2**c * z**e
        for a, b in PUPIL_TERMS
        for c in range(FIELD_DEGREE + 1)
        for e in range(depth_degree + 1)
    ]
    return np.stack(columns, -1)


@dataclass(frozen=True)
class NodalWavefront:
    """W(p; h, z) = nodal_terms(p, h, z) · ``coefficients`` (waves), h from ``axis_mm``."""

    coefficients: np.ndarray
    axis_mm: tuple[float, float]
    depth_degree: int = 2

    def __call__(self, p: np.ndarray, position_mm: Sequence[float]) -> np.ndarray:
        """W (waves) at pupil points ``p`` (n, 2) for one source position (x, y, z) mm (the field and
        depth factors summed first: one pupil column per (a, b))."""
        h = np.array([position_mm[0] - self.axis_mm[0], position_mm[1] - self.axis_mm[1]])
        z = float(position_mm[2])
        factors = np.array([(h @ h) ** c * z**e for c in range(FIELD_DEGREE + 1) for e in range(self.depth_degree + 1)])
        per_term = self.coefficients.reshape(len(PUPIL_TERMS), -1) @ factors
        p = np.asarray(p, float)
        p2, hp = (p * p).sum(-1), p @ h
        return sum(weight * p2**a * hp**b for (a, b), weight in zip(PUPIL_TERMS, per_term, strict=True))


def fit_wavefront(
    pupils: Sequence[PupilSamples], axis_mm: tuple[float, float], depth_degree: int = 2, seed: int = 0
) -> NodalWavefront:
    """The nodal wavefront fitted to ``pupils`` by least squares, weighted by |A|², each node's
    piston and tilt free (projected out per node), ≤ :data:`FIT_SAMPLES_PER_NODE` samples each."""
    rng = np.random.default_rng(seed)
    rows, values = [], []
    for pupil in pupils:
        n = len(pupil.wavefront_waves)
        pick = rng.choice(n, size=min(FIT_SAMPLES_PER_NODE, n), replace=False)
        p = pupil.p[pick]
        weight = pupil.amplitude[pick] ** 2
        root = np.sqrt(weight / weight.sum())
        h = np.array(pupil.position_mm[:2]) - np.asarray(axis_mm)
        terms = nodal_terms(p, h, pupil.position_mm[2], depth_degree=depth_degree) * root[:, None]
        target = pupil.wavefront_waves[pick] * root
        q = np.linalg.qr(np.column_stack([np.ones(len(p)), p]) * root[:, None])[0]  # the node's piston and tilt
        rows.append(terms - q @ (q.T @ terms))
        values.append(target - q @ (q.T @ target))
    X, y = np.concatenate(rows), np.concatenate(values)
    scale = np.linalg.norm(X, axis=0)
    live = scale > 1e-9 * scale.max()
    coefficients = np.zeros(X.shape[1])
    coefficients[live] = np.linalg.lstsq(X[:, live] / scale[live], y, rcond=None)[0] / scale[live]
    return NodalWavefront(coefficients, (float(axis_mm[0]), float(axis_mm[1])), depth_degree)


def pupil_extents(p: np.ndarray, spacing: float) -> np.ndarray:
    """(8,) extent of the passed samples ``p`` (n, 2) along each of :data:`DIRECTIONS`, half a sample past the last."""
    return (np.asarray(p) @ DIRECTIONS.T).max(axis=0) + 0.5 * spacing


def _cell_features(position: np.ndarray) -> np.ndarray:
    x, y, z = np.moveaxis(np.atleast_2d(position), -1, 0)
    return np.stack([np.ones_like(x), x, y, x * x, y * y, x * y, z, x * z, y * z], -1)


def _clip_features(position: np.ndarray) -> np.ndarray:
    x, y, z = np.moveaxis(np.atleast_2d(position), -1, 0)
    return np.stack([np.ones_like(x), x, y, z, x * z, y * z], -1)


def _implied_diagonals(axis_extents: np.ndarray) -> np.ndarray:
    """(..., 4) extents along the diagonals (45°, 135°, 225°, 315°) of the rectangle with the axis
    extents (..., 4) along +x, +y, −x, −y."""
    e = axis_extents
    return np.stack(
        [e[..., 0] + e[..., 1], e[..., 2] + e[..., 1], e[..., 2] + e[..., 3], e[..., 0] + e[..., 3]], -1
    ) / np.sqrt(2)


@dataclass(frozen=True)
class Aperture:
    """The passed region: e_k(x, y, z) = min(cell_k · f, clip · g for clip in clips_k), f and g the
    cell (9) and clip (6) features of the position; along a diagonal also at most the corner of the
    axis extents' rectangle. cell (8, 9); clips: 8 lists of (6,) arrays."""

    cell: np.ndarray
    clips: tuple[tuple[np.ndarray, ...], ...]

    def extents(self, position_mm: np.ndarray) -> np.ndarray:
        """(..., 8) extents (pupil units) at positions (..., 3) mm."""
        position = np.asarray(position_mm, float)
        f, g = _cell_features(position), _clip_features(position)
        e = f @ self.cell.T
        for k, clips in enumerate(self.clips):
            for clip in clips:
                e[:, k] = np.minimum(e[:, k], g @ clip)
        e[:, 1::2] = np.minimum(e[:, 1::2], _implied_diagonals(e[:, 0::2]))
        return e.reshape(position.shape[:-1] + (8,))

    def mask(self, p: np.ndarray, position_mm: Sequence[float]) -> np.ndarray:
        """Whether pupil points ``p`` (..., 2) pass at one position."""
        e = self.extents(np.asarray(position_mm, float))
        return np.all(np.asarray(p) @ DIRECTIONS.T <= e, axis=-1)


def _upper_envelope(
    features: np.ndarray, extents: np.ndarray, tolerance: float, ceiling: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """The 'not clipped' nodes (within ``tolerance`` of min(cell, ``ceiling``)) and the cell
    coefficients: least squares on the unclipped nodes that the ceiling (a diagonal's corner of
    the axis extents) does not explain, starting from the upper half of the extents."""
    free = np.ones(len(extents), bool) if ceiling is None else extents < ceiling - tolerance
    if free.sum() < features.shape[1]:  # the ceiling explains (nearly) every node: a flat cell above it
        coefficients = np.zeros(features.shape[1])
        coefficients[0] = extents.max() + tolerance
        return np.ones(len(extents), bool), coefficients
    use = extents >= np.median(extents[free])
    coefficients = np.linalg.lstsq(features[use & free], extents[use & free], rcond=None)[0]
    for _ in range(20):
        reference = features @ coefficients
        if ceiling is not None:
            reference = np.minimum(reference, ceiling)
        new = extents >= reference - tolerance
        if (new == use).all():
            break
        use = new
        coefficients = np.linalg.lstsq(features[use & free], extents[use & free], rcond=None)[0]
    return use, coefficients


def _clip_pieces(
    g: np.ndarray, extents: np.ndarray, clipped: np.ndarray, side: np.ndarray, tolerance: float
) -> list[np.ndarray]:
    """Up to two linear clip pieces (one per side of the lenslet's axis along the direction), each
    the least-squares fit to the nodes it clips subject to not cutting the others by > ``tolerance``."""
    need = 2 * g.shape[1]
    groups = [group for group in (clipped & side, clipped & ~side) if group.sum() >= need]
    pieces = [np.linalg.lstsq(g[group], extents[group], rcond=None)[0] for group in groups]
    for _ in range(5):  # reassign the clipped nodes to the piece that cuts them most
        if len(pieces) < 2:
            break
        assign = np.argmin(np.stack([g @ c for c in pieces]), 0)
        new = [clipped & (assign == i) for i in range(len(pieces))]
        if min(group.sum() for group in new) < need:
            break
        groups, pieces = new, [np.linalg.lstsq(g[group], extents[group], rcond=None)[0] for group in new]
    constrained = []
    for group, start in zip(groups, pieces, strict=True):
        a, b = g[~group], extents[~group] - tolerance
        gg, eg = g[group], extents[group]
        result = minimize(
            lambda c, gg=gg, eg=eg: ((gg @ c - eg) ** 2).sum(),
            start,
            jac=lambda c, gg=gg, eg=eg: 2 * gg.T @ (gg @ c - eg),
            constraints=[{"type": "ineq", "fun": lambda c, a=a, b=b: a @ c - b, "jac": lambda c, a=a: a}],
            method="SLSQP",
            options={"maxiter": 200},
        )
        constrained.append(result.x)
    return constrained


def fit_aperture(positions_mm: np.ndarray, extents: np.ndarray, axis_mm: Sequence[float], tolerance: float) -> Aperture:
    """The passed region fitted to traced extents (N, 8) at ``positions_mm`` (N, 3): per direction
    the unclipped nodes' smooth upper envelope, then the clipped ones' pieces (:class:`Aperture`);
    ``tolerance`` (pupil units): how far below the envelope a node counts as clipped."""
    positions, extents = np.asarray(positions_mm, float), np.asarray(extents, float)
    f, g = _cell_features(positions), _clip_features(positions)
    field = positions[:, :2] - np.asarray(axis_mm, float)
    cell = np.zeros((8, f.shape[1]))
    clips: list[tuple[np.ndarray, ...]] = [()] * 8
    for k in (0, 2, 4, 6, 1, 3, 5, 7):  # the axes first: their rectangle bounds the diagonals
        corner = None
        if k % 2:
            corner = _implied_diagonals(Aperture(cell, tuple(clips)).extents(positions)[:, 0::2])[:, k // 2]
        unclipped, cell[k] = _upper_envelope(f, extents[:, k], tolerance, corner)
        pieces = _clip_pieces(g, extents[:, k], ~unclipped, field @ DIRECTIONS[k] > 0, tolerance)
        if k % 2 and pieces:  # a diagonal piece only where it beats the corner the axes imply
            smooth = np.minimum(f @ cell[k], corner)
            cut = np.minimum(smooth, np.min(np.stack([g @ c for c in pieces]), 0))
            if ((cut - extents[:, k]) ** 2).mean() >= ((smooth - extents[:, k]) ** 2).mean():
                pieces = []
        clips[k] = tuple(pieces)
    return Aperture(cell, tuple(clips))


def pixel_integrate(image: np.ndarray, oversample: int) -> np.ndarray:
    """``image`` (fine samples, S per pixel) integrated over one pixel centred on each sample (the
    trapezoid rule over S + 1 samples), normalised so that a constant stays constant. S must be
    even (an odd S puts the pixel's edges between samples)."""
    if oversample < 2 or oversample % 2:
        raise ValueError(f"oversample = {oversample}: the pixel integral needs an even number of samples per pixel")
    kernel = np.ones(oversample + 1)
    kernel[[0, -1]] = 0.5
    kernel /= oversample
    return convolve1d(convolve1d(image, kernel, axis=0, mode="constant"), kernel, axis=1, mode="constant")


def core_centroid(image: np.ndarray, sample_mm: float) -> np.ndarray:
    """(x, y) mm of the centroid of ``image``'s part above :data:`CORE_LEVEL` of its peak, from the
    centre sample (index n // 2 along each axis)."""
    core = np.where(image >= CORE_LEVEL * image.max(), image, 0.0)
    total = core.sum()
    rows, cols = (np.arange(n) - n // 2 for n in image.shape)
    return np.array([(core.sum(0) * cols).sum(), (core.sum(1) * rows).sum()]) * sample_mm / total


def placement_features(position_mm: np.ndarray) -> np.ndarray:
    """(..., 16) cubic polynomial features of positions (..., 3) mm: 1, x, y, z and their products up to the cubes."""
    x, y, z = np.moveaxis(np.asarray(position_mm, float), -1, 0)
    one = np.ones_like(x)
    return np.stack(
        [
            one,
            x,
            y,
            z,
            x * x,
            y * y,
            x * y,
            x * z,
            y * z,
            z * z,
            x * x * z,
            y * y * z,
            x**3,
            y**3,
            x * x * y,
            x * y * y,
        ],
        -1,
    )


@dataclass(frozen=True)
class LensletModel:
    """One lenslet's model: ``wavefront``, ``aperture``, ``wavelength_mm``; the render's grid
    (``shape`` fine samples of ``sample_mm``, ``oversample`` per pixel); placement: offset (16, 2)
    and log flux (16,) coefficients of :func:`placement_features` (zero until :func:`fit_placement`)."""

    wavefront: NodalWavefront
    aperture: Aperture
    wavelength_mm: float
    shape: tuple[int, int]
    sample_mm: float
    oversample: int
    offset: np.ndarray | None = None
    log_flux: np.ndarray | None = None

    def render(self, position_mm: Sequence[float], offset_mm: Sequence[float] = (0.0, 0.0)) -> np.ndarray:
        """The unit-amplitude PSF (pixel-integrated, fine grid) at a source position, its
        reference point at ``offset_mm`` from the grid's centre sample; zeros where nothing passes.
        The Debye sum is taken on q sub-samples per fine sample (each ≤ :data:`MAX_SUBSAMPLE_MM`,
        so that the diffraction core is resolved), integrated over one pixel, then every q-th kept;
        the pupil is sampled finely enough that the sum's period λ/ΔL exceeds the window by
        :data:`PERIOD_MARGIN`."""
        q = max(1, math.ceil(self.sample_mm / MAX_SUBSAMPLE_MM - 1e-9))
        window_mm = max(self.shape) * self.sample_mm
        per_unit = max(RENDER_SAMPLES_PER_UNIT, math.ceil(PERIOD_MARGIN * window_mm * PUPIL_UNIT / self.wavelength_mm))
        axis = np.arange(-RENDER_HALF_WIDTH, RENDER_HALF_WIDTH + 1e-9, 1.0 / per_unit)
        px, py = np.meshgrid(axis, axis)
        grid = np.stack([px, py], -1)
        inside = self.aperture.mask(grid, position_mm)
        if not inside.any():
            return np.zeros(self.shape)
        field = np.zeros(px.shape, complex)
        field[inside] = np.exp(2j * np.pi * self.wavefront(grid[inside], position_mm))
        ys, xs = ((np.arange(n * q) - (n // 2) * q) * (self.sample_mm / q) for n in self.shape)
        image = mft(
            field,
            axis * PUPIL_UNIT,
            axis * PUPIL_UNIT,
            xs - offset_mm[0],
            ys - offset_mm[1],
            self.wavelength_mm,
            PUPIL_UNIT / per_unit,
        )
        return pixel_integrate(image, self.oversample * q)[::q, ::q]

    def predict(self, position_mm: Sequence[float]) -> np.ndarray:
        """The PSF at a source position: rendered at the fitted offset, scaled to the fitted flux
        (that of the unshifted render × e^{log flux}, the window's cut not counted)."""
        if self.offset is None or self.log_flux is None:
            raise ValueError("the model's placement is not fitted (fit_placement)")
        f = placement_features(np.asarray(position_mm, float))
        centred = self.render(position_mm)
        image = self.render(position_mm, tuple(f @ self.offset))
        total = image.sum()
        return image * (np.exp(f @ self.log_flux) * centred.sum() / total) if total > 0 else image


def fit_placement(
    model: LensletModel,
    crops: Sequence[np.ndarray],
    positions_mm: np.ndarray,
    trim_mm: float | None = None,
    samplers: Sequence[Callable[[np.ndarray], np.ndarray]] | None = None,
    rounds: int = 3,
) -> LensletModel:
    """``model`` with its placement fitted to the scan's ``crops`` (fine grid, as the render's) at
    ``positions_mm`` (N, 3): each crop's core centroid minus the unshifted render's (no matched
    render) and log(crop flux / render flux), as cubic polynomials in (x, y, z) by trimmed least
    squares (3 rounds; a node is dropped where it misses by > max(3 × median, ``trim_mm``), default
    two samples). Dark crops and positions where the model passes nothing are skipped.

    ``samplers``: crops on another grid than the render's, e.g. whole-pixel frames (a measured scan
    has no fine ePSF): per crop, the map of a fine render onto that crop's grid (its pixels at the
    node's sub-pixel phase); the centroids are then taken on that grid (``model.sample_mm`` ×
    ``model.oversample`` per sample), and since a centroid of coarse samples does not move one for
    one with the source, the offset is refined ``rounds`` − 1 times against the render moved by
    the offset found so far; the flux is the crop's over the sampled render's."""
    trim_mm = 2 * model.sample_mm if trim_mm is None else trim_mm
    crop_sample_mm = model.sample_mm * (model.oversample if samplers is not None else 1)
    features, offsets, fluxes = [], [], []
    for i, (crop, position) in enumerate(zip(crops, np.asarray(positions_mm, float), strict=True)):
        crop = np.asarray(crop, float)
        if not crop.sum() > 0:
            continue
        render = model.render(position)
        if not render.sum() > 0:
            continue
        sample = samplers[i] if samplers is not None else None
        target = core_centroid(crop, crop_sample_mm)
        offset = target - core_centroid(render if sample is None else sample(render), crop_sample_mm)
        flux = crop.sum() / render.sum()
        if sample is not None:
            moved = sample(model.render(position, tuple(offset)))
            for _ in range(rounds - 1):
                offset = offset + target - core_centroid(moved, crop_sample_mm)
                moved = sample(model.render(position, tuple(offset)))
            flux = crop.sum() / moved.sum() if moved.sum() > 0 else flux
        features.append(placement_features(position))
        offsets.append(offset)
        fluxes.append(np.log(flux))
    if len(features) < 2 * placement_features(np.zeros(3)).size:
        raise ValueError(f"{len(features)} lit crops cannot fit a lenslet's placement (16 terms)")
    F, offsets, fluxes = np.array(features), np.array(offsets), np.array(fluxes)
    good = np.ones(len(F), bool)
    for _ in range(3):
        offset = np.linalg.lstsq(F[good], offsets[good], rcond=None)[0]
        log_flux = np.linalg.lstsq(F[good], fluxes[good], rcond=None)[0]
        miss = np.linalg.norm(F @ offset - offsets, axis=1)
        good = miss <= max(3 * np.median(miss), trim_mm)
    return replace(model, offset=offset, log_flux=log_flux)


def fit_lenslet_model(
    pupils: Sequence[PupilSamples],
    axis_mm: tuple[float, float],
    shape: tuple[int, int],
    sample_mm: float,
    oversample: int,
) -> LensletModel:
    """A lenslet's wavefront and aperture fitted to its traced ``pupils`` (the placement not yet
    fitted); the aperture's clip tolerance: two pupil samples."""
    wavefront = fit_wavefront(pupils, axis_mm)
    positions = np.array([pupil.position_mm for pupil in pupils])
    extents = np.array([pupil.passed_extents() for pupil in pupils])
    tolerance = 2 * float(np.median([pupil.spacing for pupil in pupils]))
    aperture = fit_aperture(positions, extents, axis_mm, tolerance)
    return LensletModel(wavefront, aperture, pupils[0].wavelength_mm, shape, sample_mm, oversample)


def trace_pupils(
    emission, positions_mm: np.ndarray, stride: int = 2, seed: int = 0, progress: Progress | None = None
) -> dict[int, list[PupilSamples]]:
    """The design's traced pupils (middle band) of every lenslet at ``positions_mm`` (N, 3) by an
    :class:`~cm2optics.emission.psf.EmissionModel`, by lenslet: every ``stride``-th sample each
    way, ≤ :data:`FIT_SAMPLES_PER_NODE` of them kept (seeded) with the extents of all; the pupil
    coordinate referenced to the lenslet's exit-pupil centre seen from each pupil's reference
    point. A lenslet that passes nothing from a position has no pupil there."""
    rng = np.random.default_rng(seed)
    band = emission._mid_band  # the design's middle band, as emission.analysis takes it
    out: dict[int, list[PupilSamples]] = {}
    for i, position in enumerate(np.asarray(positions_mm, float)):
        for pupil in emission.pupils(tuple(position), bands=[band]):
            centre = emission._exit_pupil(pupil.lenslet, band)
            L, M = np.meshgrid(pupil.l_axis, pupil.m_axis)
            passed = pupil.amplitude > 0
            kept = np.zeros_like(passed)
            kept[::stride, ::stride] = True
            passed &= kept
            d = np.array([centre[0] - pupil.x_ref_mm, centre[1] - pupil.y_ref_mm, centre[2]])
            L0, M0 = -d[:2] / np.linalg.norm(d)
            p = np.column_stack([(L[passed] - L0) / PUPIL_UNIT, (M[passed] - M0) / PUPIL_UNIT])
            spacing = pupil.spacing * stride / PUPIL_UNIT
            pick = rng.choice(len(p), size=min(FIT_SAMPLES_PER_NODE, len(p)), replace=False)
            samples = PupilSamples(
                tuple(float(v) for v in position),
                p[pick],
                pupil.wavefront_mm[passed][pick] / pupil.wavelength_mm,
                pupil.amplitude[passed][pick],
                spacing,
                pupil.wavelength_mm,
                pupil_extents(p, spacing),
            )
            out.setdefault(pupil.lenslet, []).append(samples)
        if progress is not None:
            progress("design pupils", i + 1, len(positions_mm))
    return out
