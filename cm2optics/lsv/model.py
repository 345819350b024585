"""The 3D-LSV model: basis PSFs, coefficients on the calibration grid, the imaging geometry,
and its provenance; saved as one HDF5 file.

The image of a source at (x, y, z) is, lenslet by lenslet, the basis PSFs weighted by the
coefficients interpolated at the source (:mod:`cm2optics.lsv.interpolate`), each focus placed
with its centre pixel ``(h//2, w//2)`` on ``r0(z) + A(z)·(x, y) + o_j(z)``
(:class:`~cm2optics.lsv.preprocess.Geometry`) by the Keys cubic kernel. Units: the model's
images are in the scan's normalised units scaled so that the in-focus image of a unit source on
the axis sums to 1 (``scale`` records the factor).

File layout: :mod:`cm2optics.formats.lsv_model` (``format = "cm2optics-lsv"``). With
``oversample`` S > 1 the ``basis`` is (K, J, h·S, w·S), an effective PSF on a grid S times finer
than the pixels, sampled at each focus's exact sub-pixel position (:mod:`cm2optics.lsv.epsf`).
A per-lenslet basis (:func:`~cm2optics.lsv.decompose.decompose_per_lenslet`) is stored in the same
layout, each of its J·K focus arrays dark but in one lenslet; every path uses, per lenslet, only the
terms with light there (:meth:`LSVModel.lenslet_terms`).
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from cm2optics.formats.emitters import Emitters
from cm2optics.formats.lsv_model import ModelError, read_lsv_model, write_lsv_model
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.focal_surface import FocalSurface
from cm2optics.lsv.interpolate import (
    chief_ray_nodes,
    refine_axis,
    refined_lenslet_coefficients,
    trilinear_coefficients,
)
from cm2optics.lsv.preprocess import Geometry
from cm2optics.lsv.rotation import rotated_lenslet_coefficients

if TYPE_CHECKING:  # pragma: no cover
    from cm2optics.lsv.operators import LSVOperator

__all__ = ["LSVModel", "ModelError", "load_model"]


@dataclass(frozen=True, eq=False)
class LSVModel:
    """basis: (K, J, h, w) float32; coefficients: (K, nz, ny, nx) float32 on the calibration
    grid ``grid_x_mm`` × ``grid_y_mm`` × ``grid_z_mm`` (sorted, mm); geometry; sensor_shape (y, x)
    px; pixel_um: image pixel pitch (µm); default_grid: the reconstruction grid by default."""

    basis: np.ndarray
    coefficients: np.ndarray
    grid_x_mm: np.ndarray
    grid_y_mm: np.ndarray
    grid_z_mm: np.ndarray
    geometry: Geometry
    sensor_shape: tuple[int, int]
    pixel_um: float
    default_grid: VolumeGrid
    scale: float = 1.0
    singular_values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nmse: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nmse_per_psf: np.ndarray = field(default_factory=lambda: np.zeros(0))
    provenance: dict[str, Any] = field(default_factory=dict)
    #: S > 1: the basis is an effective PSF on a grid S times finer than the pixels (:mod:`.epsf`).
    oversample: int = 1
    #: Each lenslet's best-focus surface (:mod:`.focal_surface`); with it the coefficients are
    #: interpolated between lateral nodes at equal defocus from the local best focus.
    focal_surface: FocalSurface | None = None
    #: With a focal surface: lateral steps of the calibration grid are cut ``refine`` times, and
    #: each lenslet's coefficients precomputed there along its surface (every path then
    #: interpolates them trilinearly along the chief rays); 1 without a surface.
    refine: int = 1
    #: True: between lateral nodes each neighbour's PSF is turned to the source's azimuth about
    #: the lenslet's axis before the blend (:mod:`.rotation`), on the grid refined ``refine`` times.
    rotate_aberrations: bool = False
    #: True: between nodes the neighbours' PSFs are blended by displacement interpolation (each
    #: warped to the interpolated focus shape first, :mod:`.warp`), on the grid refined ``refine`` times.
    warp_shapes: bool = False
    #: With ``rotate_aberrations`` or ``warp_shapes``: the turned (warped) coefficients (J, K, nz, ny', nx') on the refined
    #: grid as computed before (saved with the model, minutes to compute at full size); None, or
    #: ones that no longer agree with ``coefficients`` at the calibration nodes: computed anew
    #: (a ``replace`` that changes the focal surface, refine or basis must pass None here).
    turned_coefficients: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not (isinstance(self.oversample, int | np.integer) and self.oversample >= 1):
            raise ModelError(f"oversample = {self.oversample!r}: must be an integer ≥ 1")
        if self.basis.shape[-1] % self.oversample or self.basis.shape[-2] % self.oversample:
            raise ModelError(
                f"basis patches {self.basis.shape[-2:]} are not a multiple of oversample = {self.oversample}"
            )
        basis = np.ascontiguousarray(self.basis, dtype=np.float32)
        coefficients = np.ascontiguousarray(self.coefficients, dtype=np.float32)
        if basis.ndim != 4:
            raise ModelError(f"basis must be (K, J, h, w), got shape {basis.shape}")
        if coefficients.ndim != 4 or coefficients.shape[0] != basis.shape[0]:
            raise ModelError(f"coefficients must be (K = {basis.shape[0]}, nz, ny, nx), got shape {coefficients.shape}")
        axes = [np.asarray(a, float) for a in (self.grid_x_mm, self.grid_y_mm, self.grid_z_mm)]
        if tuple(len(a) for a in axes[::-1]) != coefficients.shape[1:]:
            raise ModelError(
                f"grid axes ({', '.join(str(len(a)) for a in axes)}) do not match coefficients {coefficients.shape}"
            )
        for name, a in zip("xyz", axes, strict=True):
            if np.any(np.diff(a) <= 0):
                raise ModelError(f"grid_{name}_mm must increase strictly")
        if basis.shape[1] != self.geometry.n_lenslets:
            raise ModelError(f"basis has {basis.shape[1]} foci, the geometry {self.geometry.n_lenslets} lenslets")
        if not (np.all(np.isfinite(basis)) and np.all(np.isfinite(coefficients))):
            raise ModelError("basis or coefficients contain NaN or infinite values")
        object.__setattr__(self, "basis", basis)
        object.__setattr__(self, "coefficients", coefficients)
        object.__setattr__(self, "grid_x_mm", axes[0])
        object.__setattr__(self, "grid_y_mm", axes[1])
        object.__setattr__(self, "grid_z_mm", axes[2])
        object.__setattr__(self, "sensor_shape", tuple(int(s) for s in self.sensor_shape))
        object.__setattr__(self, "_operators", {})
        lit = np.abs(basis).reshape(basis.shape[0], basis.shape[1], -1).max(axis=2) > 0  # (K, J)
        object.__setattr__(self, "_lenslet_terms", tuple(np.flatnonzero(lit[:, j]) for j in range(basis.shape[1])))
        self._set_interpolation_grid()

    def _set_interpolation_grid(self) -> None:
        """Check the focal surface and refinement; precompute each lenslet's refined coefficients."""
        surface, refine = self.focal_surface, self.refine
        rotate, warp = bool(self.rotate_aberrations), bool(self.warp_shapes)
        if not (isinstance(refine, int | np.integer) and 1 <= refine <= 64):
            raise ModelError(f"refine = {refine!r}: must be an integer within 1–64")
        if (rotate or warp) and refine < 2:
            raise ModelError(
                "rotate_aberrations and warp_shapes need refine ≥ 2 (the PSFs are blended on the refined grid)"
            )
        if surface is None and not (rotate or warp):
            if refine != 1:
                raise ModelError(f"refine = {refine}: needs a focal surface (refine 1 without one)")
            object.__setattr__(self, "_interpolation", (self.axes, None))
            return
        if surface is not None and not isinstance(surface, FocalSurface):
            raise ModelError(f"focal_surface must be a FocalSurface, got {type(surface).__name__}")
        if surface is not None and surface.n_lenslets != self.n_lenslets:
            raise ModelError(f"focal surface has {surface.n_lenslets} lenslets, the basis {self.n_lenslets}")
        if rotate or warp:
            axes = tuple(refine_axis(a, int(refine)) for a in self.axes[:2]) + (self.grid_z_mm,)
            coefficients = self.turned_coefficients
            if not _agrees_at_nodes(coefficients, self.coefficients, self.n_lenslets, int(refine)):
                axes, coefficients = rotated_lenslet_coefficients(
                    self.coefficients,
                    self.basis,
                    self.axes,
                    self.geometry,
                    surface,
                    int(refine),
                    turn=rotate,
                    warp=warp,
                )
            object.__setattr__(self, "turned_coefficients", coefficients)
        else:
            axes, coefficients = refined_lenslet_coefficients(self.coefficients, self.axes, surface, int(refine))
        object.__setattr__(self, "_interpolation", (axes, coefficients))

    # -- shape ------------------------------------------------------------------------------
    @property
    def rank(self) -> int:
        return self.basis.shape[0]

    @property
    def n_lenslets(self) -> int:
        return self.basis.shape[1]

    @property
    def patch_shape(self) -> tuple[int, int]:
        """Patch size in image pixels (the basis holds ``oversample`` × as many samples)."""
        return self.basis.shape[2] // self.oversample, self.basis.shape[3] // self.oversample

    def lenslet_terms(self, lenslet: int) -> np.ndarray:
        """Indices of the basis PSFs with light in ``lenslet``: all K for a basis of focus arrays,
        that lenslet's own terms for a per-lenslet basis (every path skips the others, dark there)."""
        return self._lenslet_terms[lenslet]  # type: ignore[attr-defined]

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Calibration grid (x, y, z), mm."""
        return self.grid_x_mm, self.grid_y_mm, self.grid_z_mm

    @property
    def interpolation_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grid (x, y, z mm) of :meth:`lenslet_coefficients`: the calibration grid, its lateral
        steps cut ``refine`` times with a focal surface."""
        return self._interpolation[0]  # type: ignore[attr-defined]

    @property
    def shared_coefficients(self) -> bool:
        """True where every lenslet interpolates the calibration grid's own coefficients (no focal
        surface, no rotation): :meth:`lenslet_coefficients` is then the same array for all."""
        return self._interpolation[1] is None  # type: ignore[attr-defined]

    def lenslet_coefficients(self, lenslet: int) -> np.ndarray:
        """(K, nz, ny, nx) float32 coefficients of ``lenslet`` on :attr:`interpolation_axes`,
        interpolated trilinearly along its chief rays by every path: the calibration grid's own,
        or, with a focal surface, precomputed along it on the refined grid."""
        refined = self._interpolation[1]  # type: ignore[attr-defined]
        return self.coefficients if refined is None else refined[lenslet]

    def outside_calibration(self, positions_mm: np.ndarray, slack: float = 0.05) -> np.ndarray:
        """(N,) True for sources (N, 3) as (x, y, z) mm outside the calibration grid's x/y/z range
        widened by ``slack`` of each axis's span on either side: where the model extrapolates. An
        axis with a single node (the LSI baseline laterally) is shift invariant: no range."""
        positions = np.asarray(positions_mm, float).reshape(-1, 3)
        outside = np.zeros(len(positions), bool)
        for k, axis in enumerate(self.axes):
            if len(axis) < 2:
                continue
            margin = slack * (axis[-1] - axis[0])
            outside |= (positions[:, k] < axis[0] - margin) | (positions[:, k] > axis[-1] + margin)
        return outside

    def warn_outside_calibration(self, positions_mm: np.ndarray, what: str = "emitters") -> int:
        """Warn (``warnings.warn``) when sources lie outside the calibrated range; returns their count."""
        count = int(np.sum(self.outside_calibration(positions_mm)))
        if count:
            ranges = ", ".join(
                f"{name} {axis[0]:g}…{axis[-1]:g}"
                for name, axis in zip(("x", "y", "z"), self.axes, strict=True)
                if len(axis) > 1
            )
            warnings.warn(
                f"{count} of {len(np.asarray(positions_mm).reshape(-1, 3))} {what} lie outside the model's calibrated "
                f"range ({ranges} mm): their images are extrapolated",
                stacklevel=2,
            )
        return count

    def truncated(self, rank: int) -> LSVModel:
        """The same model keeping its first ``rank`` basis PSFs."""
        if not 1 <= rank <= self.rank:
            raise ModelError(f"rank = {rank}: must lie within 1–{self.rank}")
        turned = None if self.turned_coefficients is None else self.turned_coefficients[:, :rank]
        return replace(self, basis=self.basis[:rank], coefficients=self.coefficients[:rank], turned_coefficients=turned)

    # -- point responses (numpy, for checks and figures) ----------------------------------
    def coefficients_at(self, x_mm, y_mm, z_mm, lenslet: int | None = None) -> np.ndarray:
        """Interpolated coefficients (…, K) at sources (x, y, z) mm: plain trilinear on the
        calibration grid, or ``lenslet``'s along its chief rays (what every path uses; along the
        focal surface if the model has one: :meth:`lenslet_coefficients`)."""
        if lenslet is None:
            return trilinear_coefficients(self.coefficients, self.axes, x_mm, y_mm, z_mm)
        nodes, weights = chief_ray_nodes(self.geometry, self.interpolation_axes, lenslet, x_mm, y_mm, z_mm)
        coefficients = self.lenslet_coefficients(lenslet)
        values = coefficients[:, nodes[..., 0], nodes[..., 1], nodes[..., 2]]  # (K, …, 8)
        return np.moveaxis((values * weights).sum(-1), 0, -1)

    def focus_patches(self, x_mm: float, y_mm: float, z_mm: float) -> np.ndarray:
        """(J, h, w) focus patches of a unit point source at (x, y, z), before placement ((J, h·S,
        w·S) fine ePSF patches for an oversampled model)."""
        out = np.zeros((self.n_lenslets,) + self.basis.shape[2:], np.float32)
        for j in range(self.n_lenslets):
            c = self.coefficients_at(x_mm, y_mm, z_mm, lenslet=j)
            out[j] = np.tensordot(c, self.basis[:, j], axes=(0, 0))
        return out

    def project(self, patches: np.ndarray) -> np.ndarray:
        """The least-squares fit (J, h·S, w·S) float64 of focus patches ``patches`` (registered as
        the basis: e.g. a traced ePSF at some point) by the basis, lenslet by lenslet: each
        lenslet's patch by the terms lit there (all K of a basis of focus arrays, whose
        coefficients every path interpolates along each lenslet's own chief ray, so they differ
        between lenslets; its own terms of a per-lenslet basis). What the model gives at that
        point with the best coefficients: its basis's error there, apart from the interpolation."""
        x = np.asarray(patches, np.float64)
        if x.shape != self.basis.shape[1:]:
            raise ValueError(f"patches {x.shape}: must be (J, h·S, w·S) = {self.basis.shape[1:]}")
        out = np.zeros_like(x)
        for j in range(self.n_lenslets):
            terms = self.lenslet_terms(j)
            B = self.basis[terms, j].reshape(len(terms), -1).astype(np.float64)
            c = np.linalg.lstsq(B.T, x[j].reshape(-1), rcond=None)[0]
            out[j] = (c @ B).reshape(x.shape[1:])
        return out

    # -- operators (torch) ----------------------------------------------------------------
    def operator(self, grid: VolumeGrid | None = None, device: str = "cpu") -> LSVOperator:
        """The forward/adjoint operator on ``grid`` (default: ``default_grid``), cached."""
        from cm2optics.lsv.operators import LSVOperator

        grid = grid or self.default_grid
        key = (grid.shape, grid.voxel_um, str(device))
        cache = self._operators  # type: ignore[attr-defined]
        if key not in cache:
            cache.clear()
            if self.oversample > 1:
                from cm2optics.lsv.epsf import EPSFOperator

                cache[key] = EPSFOperator(self, grid, device=device)
            else:
                cache[key] = LSVOperator(self, grid, device=device)
        return cache[key]

    def forward(self, volume, grid: VolumeGrid | None = None, **options):
        """Sensor image(s) of ``volume`` ((B,) z, y, x) on ``grid`` (see :class:`LSVOperator`)."""
        return self.operator(grid).forward(volume, **options)

    def adjoint(self, image, grid: VolumeGrid | None = None, **options):
        """Adjoint of :meth:`forward`: volume(s) from sensor image(s) ((B,) y, x)."""
        return self.operator(grid).adjoint(image, **options)

    def forward_per_lenslet(self, volume, grid: VolumeGrid | None = None, **options):
        """The J crosstalk-free images ((B,) J, y, x), one per lenslet."""
        return self.operator(grid).forward(volume, per_lenslet=True, **options)

    def forward_sparse(self, emitters: Emitters, **options):
        """Sensor image of sparse emitters (balls) without a volume (:mod:`cm2optics.lsv.sparse`)."""
        from cm2optics.lsv.sparse import render_emitters

        return render_emitters(self, emitters, **options)

    def point_image(self, x_mm: float, y_mm: float, z_mm: float, per_lenslet: bool = False) -> np.ndarray:
        """Image (y, x) (or (J, y, x)) of a unit point source at (x, y, z) mm, float64 numpy."""
        from cm2optics.lsv.sparse import point_image

        return point_image(self, x_mm, y_mm, z_mm, per_lenslet=per_lenslet)

    # -- files ------------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the model as one HDF5 (or ``.npz``) file, atomically (:mod:`cm2optics.formats.lsv_model`)."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        fields["geometry"] = self.geometry.to_arrays()
        fields["focal_surface"] = None if self.focal_surface is None else self.focal_surface.to_arrays()
        return write_lsv_model(path, fields)


def _agrees_at_nodes(turned: np.ndarray | None, coefficients: np.ndarray, n_lenslets: int, refine: int) -> bool:
    """True if ``turned`` (J, K, nz, ny', nx') holds, at every R-th refined node, the calibration
    nodes' own ``coefficients`` (K, nz, ny, nx) for every lenslet (a turn changes nothing there)."""
    K, nz, ny, nx = coefficients.shape
    shape = (n_lenslets, K, nz, (ny - 1) * refine + 1, (nx - 1) * refine + 1)
    if turned is None or tuple(np.shape(turned)) != shape:
        return False
    at_nodes = np.asarray(turned)[:, :, :, ::refine, ::refine]
    scale = float(np.abs(coefficients).max()) or 1.0
    return bool(np.allclose(at_nodes, coefficients[None], rtol=0.0, atol=1e-5 * scale))


def load_model(path: str | Path) -> LSVModel:
    """Read a model file written by :meth:`LSVModel.save`; a bad file raises :class:`ModelError`."""
    fields = read_lsv_model(path)
    try:
        fields["geometry"] = Geometry.from_arrays(fields["geometry"])
        if fields.get("focal_surface") is not None:
            fields["focal_surface"] = FocalSurface(**fields["focal_surface"])
        return LSVModel(**fields)
    except ModelError as error:
        raise ModelError(f"{path}: {error}") from None
    except (KeyError, ValueError) as error:
        raise ModelError(f"{path}: not a readable LSV model ({error})") from None
