"""From a PSF scan to registered focus crops: dark, background and exposure; the imaging
geometry (where each lenslet's focus lands, the axial shear); crops around the chief rays.

**Geometry.** Focus ``j`` of a point source at object position (x, y, z) (mm) lands on the
sensor at ``r0(z) + A(z)·(x, y) + o_j(z)`` (row, col pixels of the scan's images), with
quadratic polynomials in z for ``r0`` (2), ``A`` (2×2: magnification, inversion and any rotation
between stage and sensor) and the lenslet offsets ``o_j`` (the axial shear). Everything is
measured from the data, nothing is taken from a design except the number of lenslets:

1. the on-axis stack (the lateral position nearest the axis) gives the foci of every lenslet
   against depth: ``r_ref(z)`` (their mean) and ``o_j(z)``, the shear the paper estimates from the
   same stack;
2. at every depth, each image's foci pattern is located by correlating it with that depth's
   lattice of foci (a comb), first near the axis and then outwards, predicted from the positions
   already found; a least-squares fit gives ``A(z)``. Before any prediction exists, the comb may
   lock onto an alias one lenslet step off (a lateral grid step of ≳ 1.4 mm moves a CM² V2's foci
   by more than half the lattice): the candidate that covers more foci wins, a tie (foci off the
   sensor) is broken by the design's magnification, and without a design it is an error.

**Misordered files.** An image whose foci sit more than a quarter of a lateral grid step away
from where its neighbours put them (a smooth cubic fit per depth), or an on-axis image that breaks
the smooth shear against depth, makes :func:`estimate_geometry` raise a :class:`ScanError` naming
the file: swapped or mislabelled images, whatever the scan's writer.

**Crops.** Each image, less its dark level, divided by its exposure and less its background
(the image median), is sampled around every focus's predicted position with the Keys cubic
kernel (:mod:`cm2optics.lsv.kernels`): a ``patch`` window whose centre pixel ``(h//2, w//2)`` is the
predicted chief-ray position. The shear is undone by construction: all crops of a lenslet are
registered on its chief ray.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from cm2optics.formats.scan import ScanError, ScanIndex
from cm2optics.lsv.crop_store import DEFAULT_MEMORY_BYTES, CropStore, crop_array
from cm2optics.lsv.kernels import sample_window

__all__ = ["Geometry", "GeometryFit", "estimate_geometry", "extract_crops", "image_background", "prepared_image"]

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class Geometry:
    """Where a point source's foci land: polynomials in z (mm), coefficients low → high order.

    r0_poly: (D+1, 2) reference position (row, col) px of a source on the axis.
    A_poly: (D+1, 2, 2) d(row, col)/d(x, y), px/mm.
    o_poly: (D+1, J, 2) offset (row, col) px of each lenslet's focus from the reference.
    rows, cols: lenslet layout (J = rows·cols, row by row).
    """

    r0_poly: np.ndarray
    A_poly: np.ndarray
    o_poly: np.ndarray
    rows: int
    cols: int

    @property
    def n_lenslets(self) -> int:
        return self.rows * self.cols

    def r0(self, z_mm: np.ndarray | float) -> np.ndarray:
        return _polyval(self.r0_poly, z_mm)

    def A(self, z_mm: np.ndarray | float) -> np.ndarray:
        return _polyval(self.A_poly, z_mm)

    def offsets(self, z_mm: np.ndarray | float) -> np.ndarray:
        return _polyval(self.o_poly, z_mm)

    def focus(self, x_mm: np.ndarray | float, y_mm: np.ndarray | float, z_mm: np.ndarray | float) -> np.ndarray:
        """(…, J, 2) focus positions (row, col) px of sources at (x, y, z) mm."""
        x, y, z = np.broadcast_arrays(np.asarray(x_mm, float), np.asarray(y_mm, float), np.asarray(z_mm, float))
        ref = self.r0(z) + np.einsum("...ab,...b->...a", self.A(z), np.stack([x, y], -1))
        return ref[..., None, :] + self.offsets(z)

    def object_from_sensor(self, position: np.ndarray, z_mm: np.ndarray | float) -> np.ndarray:
        """(…, 2) object (x, y) mm of the source at depth ``z_mm`` whose reference point lands at
        ``position`` (…, 2) (row, col) px."""
        z = np.asarray(z_mm, float)
        inverse = np.linalg.inv(self.A(z))
        return np.einsum("...ab,...b->...a", inverse, np.asarray(position, float) - self.r0(z))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "r0_poly": self.r0_poly,
            "A_poly": self.A_poly,
            "o_poly": self.o_poly,
            "layout": np.array([self.rows, self.cols]),
        }

    @classmethod
    def from_arrays(cls, data: dict[str, np.ndarray]) -> Geometry:
        rows, cols = (int(v) for v in np.asarray(data["layout"]))
        return cls(
            np.asarray(data["r0_poly"], float),
            np.asarray(data["A_poly"], float),
            np.asarray(data["o_poly"], float),
            rows,
            cols,
        )


def _polyval(coefficients: np.ndarray, z: np.ndarray | float) -> np.ndarray:
    z = np.asarray(z, float)
    out = np.zeros(z.shape + coefficients.shape[1:])
    for power in range(len(coefficients) - 1, -1, -1):
        out = out * z[(...,) + (None,) * (coefficients.ndim - 1)] + coefficients[power]
    return out


def _polyfit(z: np.ndarray, values: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares polynomial (low → high order) through values (n, …) at z (n,)."""
    degree = min(degree, len(np.unique(z)) - 1)
    basis = np.vander(z, degree + 1, increasing=True)
    flat = values.reshape(len(z), -1)
    coefficients, *_ = np.linalg.lstsq(basis, flat, rcond=None)
    return coefficients.reshape((degree + 1,) + values.shape[1:])


@dataclass(frozen=True)
class GeometryFit:
    """The fitted geometry with what the fit saw.

    geometry: the fitted :class:`Geometry`.
    axis_position_mm: (x0, y0) of the on-axis stack.
    translations_px: (N, 2) measured pattern translation of every image (NaN where dark).
    bright: (N,) images with a detectable focus pattern.
    residual_px: (N,) distance of each translation from the smooth per-depth fit (NaN where dark).
    shear_residual_px: RMS residual of the on-axis foci from their polynomials in z.
    pitch_px: mean distance between neighbouring foci in the in-focus on-axis image.
    notes: things a user should know (fallbacks used), one line each.
    """

    geometry: Geometry
    axis_position_mm: tuple[float, float]
    translations_px: np.ndarray
    bright: np.ndarray
    residual_px: np.ndarray
    shear_residual_px: float
    pitch_px: float
    notes: tuple[str, ...] = ()


# ----------------------------------------------------------------------------- images


def image_background(image: np.ndarray) -> float:
    """Background of a normalised image: the median of (a subsample of) its pixels."""
    flat = image.ravel()
    step = max(1, flat.size // 20_000)
    return float(np.median(flat[::step]))


def prepared_image(index: ScanIndex, i: int) -> np.ndarray:
    """Image ``i`` less dark level, divided by exposure and less its background (counts/ms)."""
    image = index.normalised(i)
    return image - np.float32(image_background(image))


def _noise_sigma(image: np.ndarray) -> float:
    flat = image.ravel()
    step = max(1, flat.size // 20_000)
    sample = flat[::step]
    return float(1.4826 * np.median(np.abs(sample - np.median(sample)))) + 1e-12


def _block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    h, w = (s // factor for s in image.shape)
    return image[: h * factor, : w * factor].reshape(h, factor, w, factor).mean(axis=(1, 3))


def _centroid(image: np.ndarray, guess: np.ndarray, radius: int) -> tuple[np.ndarray, float]:
    """Thresholded intensity centroid (row, col) near ``guess`` and the peak value there."""
    r0, c0 = int(round(guess[0])), int(round(guess[1]))
    rs = slice(max(r0 - radius, 0), min(r0 + radius + 1, image.shape[0]))
    cs = slice(max(c0 - radius, 0), min(c0 + radius + 1, image.shape[1]))
    window = image[rs, cs]
    if window.size == 0:
        return np.array(guess, float), 0.0
    peak = float(window.max())
    weights = np.clip(window - 0.2 * peak, 0, None)
    total = float(weights.sum())
    if total <= 0:
        return np.array(guess, float), peak
    rr, cc = np.mgrid[rs, cs]
    return np.array([(weights * rr).sum() / total, (weights * cc).sum() / total]), peak


# ----------------------------------------------------------------------------- foci on the axis


def _find_lattice(image: np.ndarray, rows: int, cols: int, name: str) -> np.ndarray:
    """The rows·cols foci (J, 2) of an in-focus on-axis image, in lattice order (row by row)."""
    n = rows * cols
    smooth = ndimage.gaussian_filter(image.astype(np.float64), 1.5)
    window = max(5, min(image.shape) // (4 * max(rows, cols)) | 1)
    peaks = (smooth == ndimage.maximum_filter(smooth, size=window)) & (smooth > 0.05 * smooth.max())
    coordinates = np.argwhere(peaks)
    values = smooth[peaks]
    order = np.argsort(values)[::-1]
    chosen: list[np.ndarray] = []
    for k in order:
        point = coordinates[k].astype(float)
        if all(np.hypot(*(point - p)) > window for p in chosen):
            chosen.append(point)
        if len(chosen) == n:
            break
    if len(chosen) < n:
        raise ScanError(
            f"{name}: the in-focus on-axis image shows {len(chosen)} foci, expected {rows}×{cols} = {n} "
            "(wrong lenslet layout, or a dark/saturated image?)"
        )
    points = np.array(chosen)
    points = points[np.argsort(points[:, 0])]
    lattice = []
    for r in range(rows):
        group = points[r * cols : (r + 1) * cols]
        lattice.append(group[np.argsort(group[:, 1])])
    lattice = np.concatenate(lattice)
    grid = lattice.reshape(rows, cols, 2)
    if rows > 1 and np.any(grid[1:, :, 0].min(axis=1) <= grid[:-1, :, 0].max(axis=1)):
        raise ScanError(f"{name}: the foci of the on-axis image do not form a {rows}×{cols} lattice")
    refined = np.array([_centroid(smooth, p, max(2, window // 4))[0] for p in lattice])
    return refined


def _pitch(lattice: np.ndarray, rows: int, cols: int) -> float:
    grid = lattice.reshape(rows, cols, 2)
    steps = []
    if cols > 1:
        steps.append(np.hypot(*np.diff(grid, axis=1).reshape(-1, 2).T))
    if rows > 1:
        steps.append(np.hypot(*np.diff(grid, axis=0).reshape(-1, 2).T))
    return float(np.mean(np.concatenate(steps))) if steps else float(min(lattice.shape))


# ----------------------------------------------------------------------------- the fit


def estimate_geometry(
    index: ScanIndex,
    rows: int,
    cols: int,
    *,
    fallback_A: Callable[[float], np.ndarray] | None = None,
    degree: int = 2,
    progress: Progress | None = None,
) -> GeometryFit:
    """Fit the imaging geometry of a scan (see the module docstring).

    rows, cols: lenslet layout.
    fallback_A: z (mm) → A (2×2 px/mm) used where the scan's lateral positions cannot fix it
        (fewer than two distinct x or y): typically the design's paraxial magnification.
    degree: polynomial degree in z (lowered to what the number of depths allows).
    progress: called as ``progress(stage, done, total)``.
    """
    xs, ys, zs = index.grid_axes_mm()
    gi = index.grid_index()
    positions = index.positions_mm
    notes: list[str] = []
    ix0 = int(np.argmin(np.abs(xs)))
    iy0 = int(np.argmin(np.abs(ys)))
    x0, y0 = float(xs[ix0]), float(ys[iy0])
    row_of = {tuple(k): n for n, k in enumerate(gi)}
    axis_rows = [row_of[(ix0, iy0, iz)] for iz in range(len(zs))]
    focus_iz = int(np.argmin(np.abs(zs)))

    # 1. the on-axis stack: foci of every lenslet against depth
    first = prepared_image(index, axis_rows[focus_iz])
    lattice = _find_lattice(first, rows, cols, index.files[axis_rows[focus_iz]])
    pitch = _pitch(lattice, rows, cols)
    smooth_sigma = max(1.0, 0.008 * pitch)
    foci = _on_axis_foci(index, axis_rows, focus_iz, lattice, pitch, smooth_sigma, progress)
    o_poly, r_poly, shear_residual = _fit_shear(index, axis_rows, zs, foci, degree)

    # 2. every depth: translation of the foci pattern, then A(z)
    factor = max(1, int(pitch // 80))
    n_images = len(index)
    translations = np.full((n_images, 2), np.nan)
    bright, prepared_ds = _downsampled_images(index, factor, max(1.0, 2.0 * smooth_sigma / factor), progress)
    lateral_ok = len(xs) >= 2 and len(ys) >= 2
    A_layers = np.zeros((len(zs), 2, 2))
    residual = np.full(n_images, np.nan)
    for iz, z in enumerate(zs):
        layer = [n for n in range(n_images) if gi[n, 2] == iz]
        layer.sort(key=lambda n: math.hypot(positions[n, 0] - x0, positions[n, 1] - y0))
        A_current, done = _track_layer(
            index, layer, float(z), (x0, y0), foci[iz], rows, cols, pitch, factor,
            prepared_ds, bright, translations, fallback_A,
        )  # fmt: skip
        if A_current is None or not lateral_ok:
            if fallback_A is None:
                raise ScanError(
                    f"the scan's positions at z = {z:g} mm cannot fix the magnification (need at least 2 × 2 lateral "
                    "positions with visible foci); give a design to fall back on"
                )
            A_layers[iz] = fallback_A(float(z))
            notes.append(f"z = {z:g} mm: magnification from the design (the scan cannot fix it)")
            continue
        A_layers[iz] = _fit_layer_A(index, float(z), (x0, y0), done, translations, residual, xs, ys)
    A_poly = _polyfit(zs, A_layers, degree)
    r0_layers = _polyval(r_poly, zs) - np.einsum("zab,b->za", _polyval(A_poly, zs), np.array([x0, y0]))
    r0_poly = _polyfit(zs, r0_layers, degree)
    geometry = Geometry(r0_poly, A_poly, o_poly, rows, cols)
    return GeometryFit(
        geometry=geometry,
        axis_position_mm=(x0, y0),
        translations_px=translations,
        bright=bright,
        residual_px=residual,
        shear_residual_px=float(np.sqrt(np.mean(shear_residual**2))),
        pitch_px=pitch,
        notes=tuple(notes),
    )


def _on_axis_foci(
    index: ScanIndex,
    axis_rows: list[int],
    focus_iz: int,
    lattice: np.ndarray,
    pitch: float,
    smooth_sigma: float,
    progress: Progress | None,
) -> np.ndarray:
    """Every lenslet's focus (px) at each depth of the on-axis stack, tracked outward from focus: (Z, L, 2)."""
    radius = max(3, int(round(0.06 * pitch)))
    foci = np.zeros((len(axis_rows), len(lattice), 2))
    foci[focus_iz] = lattice
    order = list(range(focus_iz + 1, len(axis_rows))) + list(range(focus_iz - 1, -1, -1))
    for count, iz in enumerate(order):
        previous = foci[iz - 1] if iz > focus_iz else foci[iz + 1]
        image = ndimage.gaussian_filter(prepared_image(index, axis_rows[iz]).astype(np.float64), smooth_sigma)
        found = []
        for j in range(len(lattice)):
            position, _ = _centroid(image, previous[j], radius)
            position, _ = _centroid(image, position, radius)
            found.append(position)
        foci[iz] = found
        if progress:
            progress("on-axis stack", count + 1, len(order))
    return foci


def _fit_shear(
    index: ScanIndex, axis_rows: list[int], zs: np.ndarray, foci: np.ndarray, degree: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Polynomials in z (mm) of the foci's offsets and mean (px), and each focus's residual (px); checks the order."""
    r_ref = foci.mean(axis=1)
    offsets = foci - r_ref[:, None, :]
    o_poly = _polyfit(zs, offsets, degree)
    r_poly = _polyfit(zs, r_ref, degree)
    shear_fit = _polyval(o_poly, zs)[:, :, :] + _polyval(r_poly, zs)[:, None, :]
    shear_residual = np.hypot(*(foci - shear_fit).reshape(-1, 2).T).reshape(len(zs), -1)
    step_shear = float(np.max(np.abs(np.diff(offsets, axis=0)))) if len(zs) > 1 else 0.0
    limit = max(1.5, 0.5 * step_shear)
    for iz in range(len(zs)):
        if len(zs) > degree + 2 and shear_residual[iz].max() > limit:
            raise ScanError(
                f"{index.files[axis_rows[iz]]} (z = {zs[iz]:g} mm on the axis): its foci are {shear_residual[iz].max():.1f} px "
                "from the smooth shear of the on-axis stack: misordered files (depths swapped?)"
            )
    return o_poly, r_poly, shear_residual


def _downsampled_images(
    index: ScanIndex, factor: int, sigma_ds: float, progress: Progress | None
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Every image block-averaged by ``factor`` and smoothed (``sigma_ds`` px), and whether its foci stand out."""
    n_images = len(index)
    bright = np.zeros(n_images, bool)
    prepared_ds: dict[int, np.ndarray] = {}
    for n in range(n_images):
        image = prepared_image(index, n)
        small = ndimage.gaussian_filter(_block_mean(image.astype(np.float64), factor), sigma_ds).astype(np.float32)
        bright[n] = float(small.max()) > 10.0 * _noise_sigma(small)
        prepared_ds[n] = small
        if progress:
            progress("reading images", n + 1, n_images)
    return bright, prepared_ds


def _track_layer(
    index: ScanIndex,
    layer: list[int],
    z: float,
    axis_xy: tuple[float, float],
    comb: np.ndarray,
    rows: int,
    cols: int,
    pitch: float,
    factor: int,
    prepared_ds: dict[int, np.ndarray],
    bright: np.ndarray,
    translations: np.ndarray,
    fallback_A: Callable[[float], np.ndarray] | None,
) -> tuple[np.ndarray | None, list[int]]:
    """Translate the on-axis foci ``comb`` (px) onto each image of one depth, nearest the axis first.

    Fills ``translations`` (px) and clears ``bright`` where no match is found; returns the running
    A (px/mm, None if never fixed) and the images matched.
    """
    positions = index.positions_mm
    steps = _alias_steps(comb, rows, cols)
    A_current: np.ndarray | None = None
    done: list[int] = []
    queue = [n for n in layer if bright[n]]
    deferred: set[int] = set()
    while queue:
        n = queue.pop(0)
        delta = positions[n, :2] - axis_xy
        if abs(delta[0]) < 1e-9 and abs(delta[1]) < 1e-9:
            translations[n] = 0.0
            done.append(n)
            continue
        if A_current is None:
            # no prediction yet: a window wider than half the lattice pitch, whose peak may be
            # an alias (the comb shifted by a lattice step), resolved by _resolve_alias
            found = _comb_peak(prepared_ds[n], comb, np.zeros(2), 0.6 * pitch, factor)
            if found is not None:
                ties = _resolve_alias(prepared_ds[n], comb, found, steps, 0.15 * pitch, factor)
                found = ties[0]
                if len(ties) > 1 and fallback_A is not None:  # the design's magnification decides
                    expected = fallback_A(z) @ delta
                    found = min(ties, key=lambda c: float(np.hypot(*(c[0] - expected))))
                elif len(ties) > 1 and n not in deferred:  # try it again once neighbours predict it
                    deferred.add(n)
                    queue.append(n)
                    continue
                elif len(ties) > 1:
                    raise ScanError(
                        f"{index.files[n]} (x = {positions[n, 0]:g}, y = {positions[n, 1]:g}, z = {z:g} mm): its "
                        "foci match the on-axis pattern about as well shifted by one lenslet step (the foci that "
                        "would tell them apart are dark or off the sensor), and no position nearer the axis fixes "
                        "the magnification: the scan's lateral grid step is too coarse; scan nearer the axis or "
                        "give a design to take the magnification from"
                    )
        else:
            found = _comb_peak(prepared_ds[n], comb, A_current @ delta, 0.3 * pitch, factor)
        if found is None:
            bright[n] = False
            continue
        translations[n] = found[0]
        done.append(n)
        if len(done) >= 3:
            D = positions[done, :2] - axis_xy
            if np.linalg.matrix_rank(D, tol=1e-6) == 2:
                A_current = np.linalg.lstsq(D, translations[done], rcond=None)[0].T
    return A_current, done


def _fit_layer_A(
    index: ScanIndex,
    z: float,
    axis_xy: tuple[float, float],
    done: list[int],
    translations: np.ndarray,
    residual: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
) -> np.ndarray:
    """One depth's A (2×2 px/mm) from its matched images; fills ``residual`` (px) and checks it."""
    positions = index.positions_mm
    D = positions[done, :2] - axis_xy
    A = np.linalg.lstsq(D, translations[done], rcond=None)[0].T
    residual[done] = _smooth_residual(D, translations[done])
    step_px = _grid_step_px(A, xs, ys)
    bad = [n for n in done if residual[n] > 0.25 * step_px]
    if bad:
        worst = max(bad, key=lambda n: residual[n])
        x, y, _ = positions[worst]
        raise ScanError(
            f"{index.files[worst]} (listed at x = {x:g}, y = {y:g}, z = {z:g} mm): its foci are {residual[worst]:.0f} px "
            f"from where the other images of that depth put them ({len(bad)} such images): misordered or mislabelled files"
        )
    return A


def _grid_step_px(A: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> float:
    """The grid's smallest step (px) between nodes more than a pixel apart: a scan whose nodes
    are dithered by a fraction of a pixel is checked at its node spacing (a file swapped within a
    dither is below the comb's precision anyway)."""
    steps = [np.diff(axis) * np.hypot(*A[:, k]) for k, axis in enumerate((xs, ys)) if len(axis) > 1]
    coarse = [float(d.min()) for d in (d[d > 1.0] for d in steps) if d.size]
    return min(coarse) if coarse else math.inf


def _smooth_residual(D: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Distance of each translation from a smooth (cubic, or lower) fit in (x, y), leaving the
    point out (so that one swapped image cannot hide in its own fit)."""
    n = len(D)
    x, y = D[:, 0], D[:, 1]
    terms = [np.ones(n), x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y, y**3]
    for count in (10, 6, 3):
        if n >= 2 * count:
            basis = np.stack(terms[:count], axis=1)
            break
    else:
        return np.zeros(n)
    out = np.zeros(n)
    coefficients, *_ = np.linalg.lstsq(basis, t, rcond=None)
    # leave-one-out residual through the hat matrix
    hat = basis @ np.linalg.pinv(basis)
    leverage = np.clip(np.diag(hat), 0, 0.95)
    raw = t - basis @ coefficients
    out[:] = np.hypot(*(raw / (1 - leverage)[:, None]).T)
    return out


def _alias_steps(comb: np.ndarray, rows: int, cols: int) -> list[np.ndarray]:
    """The lattice steps (px) by which the foci comb ``comb`` (J, 2) can be shifted onto itself
    in part: ±row step, ±column step and their sums."""
    grid = comb.reshape(rows, cols, 2)
    vectors = []
    if cols > 1:
        vectors.append(np.diff(grid, axis=1).reshape(-1, 2).mean(axis=0))
    if rows > 1:
        vectors.append(np.diff(grid, axis=0).reshape(-1, 2).mean(axis=0))
    if not vectors:  # a single lenslet: no lattice to alias on
        return []
    if len(vectors) == 1:
        return [vectors[0], -vectors[0]]
    return [a * vectors[0] + b * vectors[1] for a in (-1, 0, 1) for b in (-1, 0, 1) if (a, b) != (0, 0)]


#: An alias must outscore the current peak by this factor to replace it; within it they tie.
ALIAS_MARGIN = 1.25


def _resolve_alias(
    image: np.ndarray,
    comb: np.ndarray,
    found: tuple[np.ndarray, float],
    steps: list[np.ndarray],
    window: float,
    factor: int,
) -> list[tuple[np.ndarray, float]]:
    """The translation among ``found``'s aliases that the image supports, first, followed by
    the aliases it cannot tell from it.

    The comb score (the brightness under the comb's teeth) has a local maximum wherever the comb
    sits a lattice step off the image's foci (all but one row or column of teeth still land on
    foci), and a search window wider than half the lattice pitch can lock onto it: a coarse
    lateral grid step (≳ 1.4 mm for a CM² V2) would give a magnification that is silently wrong.
    At the true translation every tooth sits on its focus, and brightness is ≥ 0, so the true
    translation outscores its aliases by the foci they miss: climb from alias to alias while the
    score grows by more than :data:`ALIAS_MARGIN`. Aliases within that margin tie with it: the
    foci that would tell them apart are dim, or off the sensor."""
    best = found
    for _ in range(6):
        candidates = [_comb_peak(image, comb, best[0] + step, window, factor) for step in steps]
        candidates = [c for c in candidates if c is not None and np.hypot(*(c[0] - best[0])) > window]
        better = [c for c in candidates if c[1] > ALIAS_MARGIN * best[1]]
        if not better:
            return [best] + [c for c in candidates if c[1] * ALIAS_MARGIN >= best[1]]
        best = max(better, key=lambda c: c[1])
    return [best]


def _comb_peak(
    image: np.ndarray, comb: np.ndarray, guess: np.ndarray, window: float, factor: int
) -> tuple[np.ndarray, float] | None:
    """Translation t (px, full resolution) maximising Σ_j image((comb_j + t)/factor) within
    ``window`` of ``guess`` (parabolic sub-sample refinement), and that maximum score; None if
    no clear peak."""
    half = int(math.ceil(window / factor))
    centre = np.round(guess / factor).astype(int)
    ts = np.arange(-half, half + 1)
    tr = centre[0] + ts
    tc = centre[1] + ts
    base = comb / factor
    score = np.zeros((len(tr), len(tc)))
    for j in range(len(comb)):
        rows = base[j, 0] + tr[:, None] + np.zeros((1, len(tc)))
        cols = base[j, 1] + tc[None, :] + np.zeros((len(tr), 1))
        score += ndimage.map_coordinates(image, [rows, cols], order=1, mode="constant", cval=0.0)
    k = np.unravel_index(int(np.argmax(score)), score.shape)
    if score[k] <= 0:
        return None
    offset = np.zeros(2)
    for axis in range(2):
        idx = list(k)
        if 0 < k[axis] < score.shape[axis] - 1:
            idx[axis] = k[axis] - 1
            left = score[tuple(idx)]
            idx[axis] = k[axis] + 1
            right = score[tuple(idx)]
            curvature = left - 2 * score[k] + right
            if curvature < 0:
                offset[axis] = 0.5 * (left - right) / curvature
    return (np.array([tr[k[0]], tc[k[1]]], float) + offset) * factor, float(score[k])


# ----------------------------------------------------------------------------- crops


def extract_crops(
    index: ScanIndex,
    geometry: Geometry,
    patch: tuple[int, int],
    *,
    progress: Progress | None = None,
    memory_bytes: int = DEFAULT_MEMORY_BYTES,
) -> np.ndarray | CropStore:
    """(N, J, h, w) float32 crops of every image around every focus's predicted position; on
    disk (:func:`~cm2optics.lsv.crop_store.crop_array`) if they take more than ``memory_bytes``."""
    h, w = patch
    J = geometry.n_lenslets
    out = crop_array((len(index), J, h, w), memory_bytes)
    crop = np.zeros((J, h, w), np.float32)
    centres = geometry.focus(index.positions_mm[:, 0], index.positions_mm[:, 1], index.positions_mm[:, 2])
    for n in range(len(index)):
        image = prepared_image(index, n)
        for j in range(J):
            crop[j] = sample_window(image, tuple(centres[n, j]), (h, w))
        out[n] = crop
        if progress:
            progress("cropping foci", n + 1, len(index))
    return out
