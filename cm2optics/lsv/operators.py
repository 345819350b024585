"""Forward and adjoint 3D-LSV operators in torch (float32, batched, memory bounded).

The model (:mod:`cm2optics.lsv.model`) is the paper's ``g = Σ_z Σ_k [M_k(·, z)·O(·, z)] ⊛ H_k(·, z)``
written lenslet by lenslet: ``g = Σ_j Σ_z Σ_k [M_jk(·, z)·R_z O_z] ⊛ T_{s_j(z)} P_jk`` where

- ``R_z`` splats object plane ``z`` onto the sensor-aligned plane grid through the geometry's
  ``A(z)`` (magnification that changes with depth, inversion, rotation): bilinear weights, or an
  exact permutation where the mapping is ±1 pixel per voxel (to 0.01 px over the field);
- ``T_s`` is the sub-pixel Keys-cubic shift by ``s_j(z)``, which places lenslet j's foci at
  ``r0(z) + o_j(z)`` (the axial shear);
- ``P_jk`` is basis PSF k's patch for lenslet j and ``M_jk`` its coefficient map, interpolated
  trilinearly along lenslet j's chief rays (:mod:`cm2optics.lsv.interpolate`) on the model's
  interpolation grid (the calibration grid, or with a focal surface its refinement, where each
  lenslet's coefficients were precomputed along the surface: :meth:`LSVModel.lenslet_coefficients`).

A naive evaluation does one full-size FFT convolution per (k, z, j) (``benchmarks/bench_lsv.py``
does exactly that as the reference). Because the chief-ray interpolation makes the lateral
weights of depth node ``g_z`` independent of the plane once the plane is sheared, the sum
factorises exactly:

1. *shear stage* (per plane, per lenslet, in the Fourier domain of a canvas): the planes, shifted
   by ``s_j(z)``, are accumulated into one image per (lenslet, depth node), ``V_{j,gz}``, with the
   depth tent weights;
2. *node stage* (per lenslet and lateral node): ``Σ_gz Q_{g,j} ⊛ (w_{g,j}·V_{j,gz})`` with the
   node PSF ``Q_{g,j} = Σ_k C_k(g)·P_jk`` and the lateral tent ``w_{g,j}``, one FFT per tile of
   two grid cells, accumulated over depth nodes in the Fourier domain.

That is J·nz plane products and J·n_nodes tile FFTs instead of K·nz·J full-size convolutions.
The adjoint runs the same stages transposed; ⟨Ax, y⟩ = ⟨x, Aᵀy⟩ holds to float32 precision.
Peak memory ≈ the volume + J·(depth nodes)·canvas complex64 accumulators + a few tiles
(:meth:`LSVOperator.memory_bytes`, :meth:`LSVOperator.transient_bytes`). Where the stage's axes
are coupled with the sensor's (a fitted ``A`` with off-diagonal terms, however small: the
'general' path) neither the splat nor the lateral tents separate into rows and columns; both are
then evaluated on the fly (the splat in chunks of voxels, the tents per tile) instead of being
stored per plane and per node, which at full size (1920 × 1920 × 80 voxels) took > 22 GB.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.interpolate import axis_coordinate, tent_pairs
from cm2optics.lsv.kernels import shift_kernel_dft

if TYPE_CHECKING:  # pragma: no cover
    from cm2optics.lsv.model import LSVModel

__all__ = ["LSVOperator", "fast_length"]

Progress = Callable[[str, int, int], None]
#: A mapping closer than this (px, over the field) to ±1 px per voxel is treated as exact.
SNAP_PX = 0.01
#: Tiles are transformed in batches of at most this many real samples (16 MB in float32): one
#: tile at a time at full size (bigger batches lose to memory bandwidth), many at small sizes.
TILE_BATCH_ELEMENTS = 2**22


def fast_length(n: int) -> int:
    """Smallest length ≥ n of the form 2^a, 3·2^a or 9·2^a: the FFT sizes that MKL and pocketfft
    transform fastest (3^6 = 729, for one, takes twice as long as 768 = 3·2^8)."""
    n = max(int(n), 1)
    best = None
    for factor in (1, 3, 9):
        length = factor
        while length < n:
            length *= 2
        best = length if best is None else min(best, length)
    return best


@dataclass
class _Axis:
    """Splat of one axis: ``n_in`` samples onto ``n_out``. Either an exact slice (``start``,
    ``step`` ±1: a permutation) or a sparse matrix (n_out × n_in, two weights per column) and its
    transpose."""

    n_in: int
    n_out: int
    start: int | None = None
    step: int | None = None
    matrix: torch.Tensor | None = None
    transpose: torch.Tensor | None = None


@dataclass
class _Splat:
    """How plane z is splatted: ``kind`` 'diag' (row ← iy, col ← ix), 'anti' (row ← ix, col ← iy)
    or 'general' (bilinear weights of the affine map ``affine`` (2, 3): plane (row, col) =
    ``affine[:, :2] @ (iy − cy, ix − cx) + affine[:, 2]``, px, evaluated on the fly, chunk by
    chunk, so that no per-plane matrix is stored)."""

    kind: str
    rows: _Axis | None = None
    cols: _Axis | None = None
    affine: np.ndarray | None = None


def _csr(
    rows: np.ndarray, cols: np.ndarray, values: np.ndarray, shape: tuple[int, int], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """A sparse CSR matrix and its transpose from COO triplets (float32)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        index = torch.as_tensor(np.stack([rows, cols]), device=device)
        data = torch.as_tensor(values, dtype=torch.float32, device=device)
        matrix = torch.sparse_coo_tensor(index, data, shape).coalesce().to_sparse_csr()
        transpose = torch.sparse_coo_tensor(index.flip(0), data, shape[::-1]).coalesce().to_sparse_csr()
    return matrix, transpose


class _TentMap:
    """The lateral weights of node (gy, gx) on a canvas box when the plane's rows and columns
    are not aligned with the calibration grid's x and y ('general'): ``tent(v − gy)·tent(u − gx)``
    with (u, v) the continuous node indices of the object point ``inverse·(p + base)`` (mm) of
    canvas pixel p = (row, col). Evaluated when used, so that the operator keeps two 2×2 numbers
    per node instead of a weight image (which, at full size, would take gigabytes): on a uniform
    calibration axis the node index is affine in (row, col) and the weights take a dozen float32
    passes over the box; an irregular axis goes through a (slower) float64 search."""

    def __init__(self, inverse, base, gy: int, gx: int, box: tuple[int, int, int, int], axes) -> None:
        self.inverse = np.asarray(inverse, dtype=np.float64)
        self.base = np.asarray(base, dtype=np.float64)
        self.gy, self.gx = gy, gx
        self.box = box
        self.axes = axes  # (grid_x_mm, grid_y_mm) float64 tensors
        self.spacing = tuple(_uniform(a.cpu().numpy()) for a in axes)

    def tensor(self) -> torch.Tensor:
        """(r1 − r0, c1 − c0) float32 weights on the box."""
        r0, r1, c0, c1 = self.box
        device = self.axes[0].device
        rows = np.arange(r0, r1, dtype=np.float64) + self.base[0]
        cols = np.arange(c0, c1, dtype=np.float64) + self.base[1]
        weight = None
        for k, (axis, g, (first, step)) in enumerate(zip(self.axes, (self.gx, self.gy), self.spacing, strict=True)):
            n = axis.numel()
            if n == 1:  # one node: its weight is 1 everywhere
                continue
            along_rows = self.inverse[k, 0] * rows  # mm
            along_cols = self.inverse[k, 1] * cols
            if step:  # the node index is affine in (row, col)
                ur = torch.as_tensor((along_rows - first) / step, dtype=torch.float32, device=device)
                uc = torch.as_tensor(along_cols / step, dtype=torch.float32, device=device)
                u = ur[:, None] + uc[None, :]
                u.clamp_(0.0, float(n - 1))
            else:
                x = (
                    torch.as_tensor(along_rows, device=device)[:, None]
                    + torch.as_tensor(along_cols, device=device)[None, :]
                )
                u = _node_coordinate(x, axis).to(torch.float32)
            u.sub_(float(g)).abs_().neg_().add_(1.0).clamp_(min=0.0)
            weight = u if weight is None else weight.mul_(u)
        if weight is None:
            weight = torch.ones((r1 - r0, c1 - c0), dtype=torch.float32, device=device)
        return weight


def _uniform(axis: np.ndarray) -> tuple[float, float]:
    """(first node, step) of a grid axis (mm) whose nodes are evenly spaced; step 0 otherwise."""
    axis = np.asarray(axis, dtype=np.float64)
    if len(axis) < 2:
        return float(axis[0]), 0.0
    step = (axis[-1] - axis[0]) / (len(axis) - 1)
    even = bool(np.all(np.abs(np.diff(axis) - step) <= 1e-9 * abs(axis[-1] - axis[0])))
    return float(axis[0]), float(step) if even else 0.0


def _node_coordinate(values: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`~cm2optics.lsv.interpolate.axis_coordinate`: the continuous node
    index of ``values`` along the sorted grid ``axis``, clamped to [0, n − 1]."""
    n = axis.numel()
    if n == 1:
        return torch.zeros_like(values)
    upper = torch.clamp(torch.searchsorted(axis, values.contiguous(), right=True), 1, n - 1)
    lower = upper - 1
    a0, a1 = axis[lower], axis[upper]
    return torch.clamp(lower + (values - a0) / (a1 - a0), 0.0, float(n - 1))


def _tent_support(
    inverse: np.ndarray,
    base: np.ndarray,
    axes: tuple[torch.Tensor, torch.Tensor],
    gy: int,
    gx: int,
    canvas: tuple[int, int],
) -> tuple[int, int, int, int] | None:
    """Canvas box (r0, r1, c0, c1) holding every pixel where node (gy, gx)'s 'general' tent is
    non-zero: the image of the node's cell (x, y) ∈ (x_{gx−1}, x_{gx+1}) × (y_{gy−1}, y_{gy+1})
    (unbounded beyond the outermost nodes, where the weights are clamped) through the affine
    map, bounded by the canvas; None if it misses the canvas."""
    xs, ys = (a.cpu().numpy() for a in axes)
    forward = np.linalg.inv(inverse)
    Hc, Wc = canvas
    corners = np.array([[0, 0], [0, Wc - 1], [Hc - 1, 0], [Hc - 1, Wc - 1]], dtype=np.float64) + base
    reach = corners @ inverse.T  # (x, y) of the canvas corners, mm
    lo_xy, hi_xy = reach.min(axis=0), reach.max(axis=0)

    def cell(axis: np.ndarray, g: int, lo: float, hi: float) -> tuple[float, float]:
        left = axis[g - 1] if g >= 1 else -np.inf
        right = axis[g + 1] if g + 1 < len(axis) else np.inf
        return max(left, lo), min(right, hi)

    x0, x1 = cell(xs, gx, lo_xy[0], hi_xy[0])
    y0, y1 = cell(ys, gy, lo_xy[1], hi_xy[1])
    if x0 >= x1 or y0 >= y1:
        return None
    points = np.array([[x0, y0], [x0, y1], [x1, y0], [x1, y1]]) @ forward.T - base  # canvas (row, col)
    r0 = max(int(np.floor(points[:, 0].min())), 0)
    r1 = min(int(np.ceil(points[:, 0].max())) + 1, Hc)
    c0 = max(int(np.floor(points[:, 1].min())), 0)
    c1 = min(int(np.ceil(points[:, 1].max())) + 1, Wc)
    if r0 >= r1 or c0 >= c1:
        return None
    return r0, r1, c0, c1


@dataclass
class _Tile:
    """Lateral node (gy, gx) of lenslet j: its box on the canvas, FFT shape, depth nodes, and
    per depth node the 1-D tent weights (rows, cols) restricted to the box (or 2-D weights)."""

    gy: int
    gx: int
    box: tuple[int, int, int, int]  # r0, r1, c0, c1 on the canvas
    fft: tuple[int, int]
    depth_nodes: list[int]
    weights: list[tuple[torch.Tensor, torch.Tensor] | _TentMap]
    out: tuple[int, int]  # sensor (row, col) of the tile output's pixel (0, 0)


class LSVOperator:
    """The model's forward and adjoint on one reconstruction grid (see the module docstring).

    model: the :class:`~cm2optics.lsv.model.LSVModel`.
    grid: the volume grid (z, y, x) with its voxel pitch.
    device: torch device.
    """

    def __init__(self, model: LSVModel, grid: VolumeGrid, device: str | torch.device = "cpu"):
        self.model = model
        self.grid = grid
        self.device = torch.device(device)
        self.sensor_shape = model.sensor_shape
        self.n_lenslets = model.n_lenslets
        geometry = model.geometry
        nz, ny, nx = grid.shape
        dz, dy, dx = (v / 1000.0 for v in grid.voxel_um)
        self.z_mm = grid.axis_mm(0)
        A = geometry.A(self.z_mm)  # (nz, 2, 2): rows (row, col), columns (x, y)
        # M maps (iy − cy, ix − cx) to (row, col) on the plane
        M = np.stack(
            [np.stack([A[:, 0, 1] * dy, A[:, 0, 0] * dx], -1), np.stack([A[:, 1, 1] * dy, A[:, 1, 0] * dx], -1)], 1
        )
        self._M = M
        half = np.array([(ny - 1) / 2.0, (nx - 1) / 2.0])
        kinds = [self._kind(M[z], half) for z in range(nz)]
        if len(set(kinds)) != 1:
            kinds = ["general"] * nz
        self._kind_all = kinds[0]
        # plane grid
        extent_r = np.max(np.abs(M[:, 0, 0]) * half[0] + np.abs(M[:, 0, 1]) * half[1])
        extent_c = np.max(np.abs(M[:, 1, 0]) * half[0] + np.abs(M[:, 1, 1]) * half[1])
        n_r, n_c = (ny, nx) if kinds[0] != "anti" else (nx, ny)
        mr = int(math.ceil(max(0.0, extent_r - (n_r - 1) / 2.0))) + 2
        mc = int(math.ceil(max(0.0, extent_c - (n_c - 1) / 2.0))) + 2
        self.plane_shape = (n_r + 2 * mr, n_c + 2 * mc)
        self.plane_centre = np.array([(self.plane_shape[0] - 1) / 2.0, (self.plane_shape[1] - 1) / 2.0])
        self._splats = [self._make_splat(M[z], kinds[z], half) for z in range(nz)]
        # shear stage: per lenslet canvas origin V_j and shifts s_j(z)
        offset = geometry.r0(self.z_mm) - self.plane_centre  # (nz, 2): sensor = plane + offset
        focus = offset[:, None, :] + geometry.offsets(self.z_mm)  # (nz, J, 2)
        self.canvas_origin = np.floor(focus.min(axis=0)).astype(np.int64) - 2  # (J, 2)
        self.shifts = focus - self.canvas_origin[None]  # (nz, J, 2), ≥ 2
        need = np.array(self.plane_shape) + self.shifts.max(axis=(0, 1)) + 3
        self.canvas_shape = (fast_length(int(math.ceil(need[0]))), fast_length(int(math.ceil(need[1]))))
        Hc, Wc = self.canvas_shape
        ky = shift_kernel_dft(self.shifts[..., 0], Hc, real=False)  # (nz, J, Hc)
        kx = shift_kernel_dft(self.shifts[..., 1], Wc, real=True)  # (nz, J, Wc//2+1)
        self._ky = torch.as_tensor(ky, dtype=torch.complex64, device=self.device)
        self._kx = torch.as_tensor(kx, dtype=torch.complex64, device=self.device)
        self._ky_conj = torch.conj(self._ky).resolve_conj()
        self._kx_conj = torch.conj(self._kx).resolve_conj()
        # depth tents
        zs = model.grid_z_mm
        lo, hi, t = tent_pairs(axis_coordinate(self.z_mm, zs), len(zs))
        self.depth_weights: list[list[tuple[int, float]]] = []
        for z in range(nz):
            pairs = {}
            for g, w in ((int(lo[z]), 1.0 - float(t[z])), (int(hi[z]), float(t[z]))):
                if w > 0:
                    pairs[g] = pairs.get(g, 0.0) + w
            self.depth_weights.append(sorted(pairs.items()))
        self.depth_nodes = sorted({g for pairs in self.depth_weights for g, _ in pairs})
        self._slot = {g: i for i, g in enumerate(self.depth_nodes)}
        # node stage
        # per lenslet the basis patches with light there (K_j, h, w): all K of a basis of focus
        # arrays, K of the J·K terms of a per-lenslet basis; and their coefficients (K_j, nz, ny,
        # nx) on the interpolation grid (one shared tensor where every lenslet has all terms)
        shared = model.shared_coefficients
        self._patches, self._coefficients = [], []
        full: dict[int, torch.Tensor] = {}
        for j in range(self.n_lenslets):
            terms = model.lenslet_terms(j)
            every = len(terms) == model.rank
            self._patches.append(
                torch.as_tensor(model.basis[:, j] if every else model.basis[terms, j], device=self.device)
            )
            key = 0 if shared else j
            if key not in full:
                full[key] = torch.as_tensor(model.lenslet_coefficients(key), device=self.device)
            self._coefficients.append(full[key] if every else full[key][torch.as_tensor(terms, device=self.device)])
        self._axes = model.interpolation_axes
        self._content = (
            int(np.floor(self.shifts[..., 0].min())) - 1,
            int(np.ceil(self.shifts[..., 0].max())) + self.plane_shape[0] + 3,
            int(np.floor(self.shifts[..., 1].min())) - 1,
            int(np.ceil(self.shifts[..., 1].max())) + self.plane_shape[1] + 3,
        )
        self._grid_xy = (
            torch.as_tensor(self._axes[0], dtype=torch.float64, device=self.device),
            torch.as_tensor(self._axes[1], dtype=torch.float64, device=self.device),
        )
        self.tiles = [self._make_tiles(j) for j in range(self.n_lenslets)]

    # -- set-up ------------------------------------------------------------------------------
    @staticmethod
    def _kind(M: np.ndarray, half: np.ndarray) -> str:
        if abs(M[0, 1]) * half[1] + abs(M[1, 0]) * half[0] < SNAP_PX:
            return "diag"
        if abs(M[0, 0]) * half[0] + abs(M[1, 1]) * half[1] < SNAP_PX:
            return "anti"
        return "general"

    def _axis(self, scale: float, centre: float, n: int, n_out: int) -> _Axis:
        c = (n - 1) / 2.0
        if abs(abs(scale) - 1.0) * c < SNAP_PX:
            scale = math.copysign(1.0, scale)
        target = centre + scale * (np.arange(n) - c)
        target = np.where(np.abs(target - np.round(target)) < 1e-9, np.round(target), target)
        lo = np.floor(target).astype(np.int64)
        weight = target - lo
        if lo.min() < 0 or lo.max() + 1 >= n_out:
            raise AssertionError("plane grid too small")  # guarded by the plane margins
        if np.all(weight == 0) and abs(scale) == 1.0:
            return _Axis(n, n_out, start=int(lo[0]), step=int(scale))
        rows = np.concatenate([lo, lo + 1])
        cols = np.concatenate([np.arange(n), np.arange(n)])
        matrix, transpose = _csr(rows, cols, np.concatenate([1 - weight, weight]), (n_out, n), self.device)
        return _Axis(n, n_out, matrix=matrix, transpose=transpose)

    def _make_splat(self, M: np.ndarray, kind: str, half: np.ndarray) -> _Splat:
        ny, nx = self.grid.shape[1:]
        Hp, Wp = self.plane_shape
        if kind == "diag":
            return _Splat(
                "diag",
                self._axis(M[0, 0], self.plane_centre[0], ny, Hp),
                self._axis(M[1, 1], self.plane_centre[1], nx, Wp),
            )
        if kind == "anti":
            return _Splat(
                "anti",
                self._axis(M[0, 1], self.plane_centre[0], nx, Hp),
                self._axis(M[1, 0], self.plane_centre[1], ny, Wp),
            )
        affine = np.array(
            [[M[0, 0], M[0, 1], self.plane_centre[0]], [M[1, 0], M[1, 1], self.plane_centre[1]]], dtype=np.float64
        )
        corners = np.array([[-half[0], -half[1]], [-half[0], half[1]], [half[0], -half[1]], [half[0], half[1]]])
        reach = corners @ affine[:, :2].T + affine[:, 2]
        if reach.min() < 0 or reach[:, 0].max() + 1 >= Hp or reach[:, 1].max() + 1 >= Wp:
            raise AssertionError("plane grid too small")  # guarded by the plane margins
        return _Splat("general", affine=affine)

    def _lateral_tents(self, j: int, gz: int) -> tuple[str, np.ndarray, np.ndarray]:
        """Lattice coordinates (continuous node indices) of every canvas row/col for lenslet j's
        chief rays at depth node gz (separable: 'diag', 'anti'); for 'general', the inverse of
        ``A(z_g)`` (mm/px) and the sensor − reference offset (px) of canvas pixel (0, 0)."""
        model = self.model
        geometry = model.geometry
        zg = model.grid_z_mm[gz]
        A = geometry.A(zg)
        base = self.canvas_origin[j] - geometry.offsets(zg)[j] - geometry.r0(zg)  # sensor − reference at canvas (0, 0)
        Hc, Wc = self.canvas_shape
        rows = np.arange(Hc) + base[0]
        cols = np.arange(Wc) + base[1]
        xs, ys = self._axes[:2]
        if abs(A[0, 0]) < 1e-12 and abs(A[1, 1]) < 1e-12:  # row ← y, col ← x
            return "diag", axis_coordinate(rows / A[0, 1], ys), axis_coordinate(cols / A[1, 0], xs)
        if abs(A[0, 1]) < 1e-12 and abs(A[1, 0]) < 1e-12:  # row ← x, col ← y
            return "anti", axis_coordinate(rows / A[0, 0], xs), axis_coordinate(cols / A[1, 1], ys)
        return "general", np.linalg.inv(A), np.asarray(base, dtype=np.float64)

    def _make_tiles(self, j: int) -> list[_Tile]:
        model = self.model
        nyc, nxc = len(self._axes[1]), len(self._axes[0])
        h, w = model.patch_shape
        H, W = self.sensor_shape
        r_lo, r_hi, c_lo, c_hi = self._content
        per_node: dict[tuple[int, int], list[tuple[int, object, tuple[int, int, int, int]]]] = {}
        for gz in self.depth_nodes:
            kind, u, v = self._lateral_tents(j, gz)
            for gy in range(nyc):
                for gx in range(nxc):
                    if kind in ("diag", "anti"):
                        along_rows, along_cols = (u, v) if kind == "diag" else (u, v)
                        wy = _tent(along_rows, gy if kind == "diag" else gx)
                        wx = _tent(along_cols, gx if kind == "diag" else gy)
                        rows = np.nonzero(wy > 0)[0]
                        cols = np.nonzero(wx > 0)[0]
                        if len(rows) == 0 or len(cols) == 0:
                            continue
                        box = (
                            max(rows[0], r_lo, 0),
                            min(rows[-1] + 1, r_hi),
                            max(cols[0], c_lo, 0),
                            min(cols[-1] + 1, c_hi),
                        )
                        weights: object = (wy, wx)
                    else:
                        support = _tent_support(u, v, self._grid_xy, gy, gx, self.canvas_shape)
                        if support is None:
                            continue
                        box = (
                            max(support[0], r_lo, 0),
                            min(support[1], r_hi),
                            max(support[2], c_lo, 0),
                            min(support[3], c_hi),
                        )
                        weights = (u, v)
                    if box[0] >= box[1] or box[2] >= box[3]:
                        continue
                    per_node.setdefault((gy, gx), []).append((gz, weights, box))
        tiles = []
        origin = self.canvas_origin[j]
        for (gy, gx), entries in per_node.items():
            box = (
                min(e[2][0] for e in entries),
                max(e[2][1] for e in entries),
                min(e[2][2] for e in entries),
                max(e[2][3] for e in entries),
            )
            out_r = box[0] + origin[0] - h // 2
            out_c = box[2] + origin[1] - w // 2
            bh, bw = box[1] - box[0], box[3] - box[2]
            if out_r >= H or out_c >= W or out_r + bh + h - 1 <= 0 or out_c + bw + w - 1 <= 0:
                continue  # the tile's light never reaches the sensor
            fft = (fast_length(bh + h - 1), fast_length(bw + w - 1))
            weights = []
            for _, weight, _ in entries:
                if weight[0].ndim == 1:
                    weights.append(
                        (
                            torch.as_tensor(weight[0][box[0] : box[1]], dtype=torch.float32, device=self.device),
                            torch.as_tensor(weight[1][box[2] : box[3]], dtype=torch.float32, device=self.device),
                        )
                    )
                else:
                    weights.append(_TentMap(weight[0], weight[1], gy, gx, box, self._grid_xy))
            tiles.append(_Tile(gy, gx, box, fft, [e[0] for e in entries], weights, (int(out_r), int(out_c))))
        return tiles

    # -- pieces -----------------------------------------------------------------------------
    def _splat(self, plane: torch.Tensor, z: int) -> torch.Tensor:
        splat = self._splats[z]
        Hp, Wp = self.plane_shape
        if splat.kind == "general":
            out = torch.zeros(Hp * Wp, dtype=plane.dtype, device=plane.device)
            for rows, index, weights in _affine_bilinear(splat.affine, plane.shape, Wp, plane.device):
                values = plane[rows].reshape(-1)
                for target, weight in zip(index, weights, strict=True):
                    out.index_add_(0, target, values * weight)
            return out.reshape(Hp, Wp)
        if splat.kind == "anti":
            plane = plane.T
        tmp = _splat_axis(plane, splat.rows)
        return _splat_axis(tmp.T, splat.cols).T

    def _gather(self, plane: torch.Tensor, z: int) -> torch.Tensor:
        splat = self._splats[z]
        if splat.kind == "general":
            ny, nx = self.grid.shape[1:]
            flat = plane.reshape(-1)
            out = torch.empty((ny, nx), dtype=plane.dtype, device=plane.device)
            for rows, index, weights in _affine_bilinear(splat.affine, (ny, nx), plane.shape[1], plane.device):
                total = flat[index[0]] * weights[0]
                for target, weight in zip(index[1:], weights[1:], strict=True):
                    total += flat[target] * weight
                out[rows] = total.reshape(-1, nx)
            return out
        tmp = _gather_axis(plane, splat.rows)
        out = _gather_axis(tmp.T, splat.cols).T
        return out.T if splat.kind == "anti" else out

    def _node_patches(self, j: int, tiles: list[_Tile]) -> torch.Tensor:
        """rfft2 of the node PSFs Q_{(gz, gy, gx), j} of ``tiles`` (one FFT shape, same depth
        nodes) at their FFT shape: (tiles, depth nodes, Fh, Fw//2+1)."""
        nodes = tiles[0].depth_nodes
        c = torch.stack([self._coefficients[j][:, nodes, tile.gy, tile.gx].T for tile in tiles])  # (t, d, K)
        K, h, w = self._patches[j].shape
        q = (c.reshape(-1, K) @ self._patches[j].reshape(K, h * w)).reshape(len(tiles), len(nodes), h, w)
        return torch.fft.rfft2(q, s=tiles[0].fft)

    def _chunks(self, j: int) -> list[list[_Tile]]:
        """Lenslet j's tiles grouped by FFT shape and depth nodes, in chunks of bounded memory."""
        cache = self.__dict__.setdefault("_chunk_cache", {})
        if j not in cache:
            groups: dict[tuple, list[_Tile]] = {}
            for tile in self.tiles[j]:
                groups.setdefault((tile.fft, tuple(tile.depth_nodes)), []).append(tile)
            chunks = []
            for (fft, nodes), tiles in groups.items():
                size = max(1, TILE_BATCH_ELEMENTS // (len(nodes) * fft[0] * fft[1]))
                chunks += [tiles[i : i + size] for i in range(0, len(tiles), size)]
            cache[j] = chunks
        return cache[j]

    @staticmethod
    def _weighted(block: torch.Tensor, weight) -> torch.Tensor:
        if isinstance(weight, tuple):
            return block * weight[0][:, None] * weight[1][None, :]
        return block * weight.tensor()

    # -- memory -----------------------------------------------------------------------------
    def memory_bytes(self) -> int:
        """Bytes the operator keeps between calls: shift kernels, basis, coefficients, the
        splats' 1-D matrices and the tiles' 1-D weights (a 'general' mapping keeps none per
        voxel or pixel: its splat and tent weights are computed when used)."""

        def size(t: torch.Tensor | None) -> int:
            if t is None:
                return 0
            if t.layout == torch.sparse_csr:
                return sum(x.numel() * x.element_size() for x in (t.values(), t.crow_indices(), t.col_indices()))
            return t.numel() * t.element_size()

        kernels = (self._ky, self._kx, self._ky_conj, self._kx_conj)
        coefficients = {id(t): t for t in self._coefficients}.values()
        total = sum(size(t) for t in (*kernels, *self._patches, *coefficients))
        for splat in self._splats:
            for axis in (splat.rows, splat.cols):
                if axis is not None:
                    total += size(axis.matrix) + size(axis.transpose)
        for tiles in self.tiles:
            for tile in tiles:
                for weight in tile.weights:
                    if isinstance(weight, tuple):
                        total += size(weight[0]) + size(weight[1])
        return int(total)

    def transient_bytes(self) -> int:
        """Peak bytes one forward or adjoint call adds (the input and output not counted): the
        J × depth-node spectra accumulators, one lenslet's canvases, a batch of tiles and a
        chunk of the 'general' splat."""
        Hc, Wc = self.canvas_shape
        n_nodes = len(self.depth_nodes)
        spectra = self.n_lenslets * n_nodes * Hc * (Wc // 2 + 1) * 8
        canvases = n_nodes * Hc * Wc * 4 + 2 * Hc * (Wc // 2 + 1) * 8
        tiles = 6 * min(TILE_BATCH_ELEMENTS, n_nodes * Hc * Wc) * 8
        voxels = self.grid.shape[1] * self.grid.shape[2]
        splat = min(SPLAT_CHUNK_ELEMENTS, voxels) * 96 if self._kind_all == "general" else 0
        return int(spectra + canvases + tiles + splat + 2 * self.plane_shape[0] * self.plane_shape[1] * 4)

    # -- forward ----------------------------------------------------------------------------
    def _as_batch(self, data, ndim: int) -> tuple[torch.Tensor, bool, bool]:
        is_numpy = not isinstance(data, torch.Tensor)
        tensor = torch.as_tensor(np.asarray(data) if is_numpy else data, dtype=torch.float32, device=self.device)
        single = tensor.ndim == ndim
        if single:
            tensor = tensor[None]
        if tensor.ndim != ndim + 1:
            raise ValueError(
                f"expected an array of {ndim} (or {ndim + 1}, batched) dimensions, got shape {tuple(tensor.shape)}"
            )
        return tensor, single, is_numpy

    def forward(self, volume, *, per_lenslet: bool = False, progress: Progress | None = None):
        """Sensor image (y, x) of a volume (z, y, x), or (B, y, x) of (B, z, y, x); with
        ``per_lenslet`` the J crosstalk-free images (…, J, y, x). numpy in, numpy out."""
        batch, single, is_numpy = self._as_batch(volume, 3)
        if tuple(batch.shape[1:]) != self.grid.shape:
            raise ValueError(f"volume shape {tuple(batch.shape[1:])} does not match the grid {self.grid.shape}")
        outputs = [self._forward_one(v, per_lenslet, progress) for v in batch]
        out = torch.stack(outputs)
        out = out[0] if single else out
        return out.cpu().numpy() if is_numpy else out

    @torch.no_grad()
    def _forward_one(self, volume: torch.Tensor, per_lenslet: bool, progress: Progress | None) -> torch.Tensor:
        J = self.n_lenslets
        Hc, Wc = self.canvas_shape
        n_nodes = len(self.depth_nodes)
        spectra = torch.zeros((J, n_nodes, Hc, Wc // 2 + 1), dtype=torch.complex64, device=self.device)
        nz = self.grid.shape[0]
        for z in range(nz):
            plane = volume[z]
            if not torch.any(plane):
                continue
            spectrum = torch.fft.rfft2(self._splat(plane, z), s=(Hc, Wc))
            for j in range(J):
                shifted = spectrum * self._kx[z, j][None, :]
                for g, a in self.depth_weights[z]:
                    spectra[j, self._slot[g]].addcmul_(shifted, self._ky[z, j][:, None], value=a)
            if progress:
                progress("forward: shear", z + 1, nz)
        H, W = self.sensor_shape
        image = torch.zeros((J if per_lenslet else 1, H, W), dtype=torch.float32, device=self.device)
        h, w = self.model.patch_shape
        for j in range(J):
            canvases = {g: torch.fft.irfft2(spectra[j, self._slot[g]], s=(Hc, Wc)) for g in self.depth_nodes}
            spectra[j] = 0
            target = image[j if per_lenslet else 0]
            for tiles in self._chunks(j):
                bh = max(t.box[1] - t.box[0] for t in tiles)
                bw = max(t.box[3] - t.box[2] for t in tiles)
                blocks = torch.zeros(
                    (len(tiles), len(tiles[0].depth_nodes), bh, bw), dtype=torch.float32, device=self.device
                )
                for i, tile in enumerate(tiles):
                    r0, r1, c0, c1 = tile.box
                    for k, (g, weight) in enumerate(zip(tile.depth_nodes, tile.weights, strict=True)):
                        blocks[i, k, : r1 - r0, : c1 - c0] = self._weighted(canvases[g][r0:r1, c0:c1], weight)
                busy = blocks.reshape(len(tiles), -1).abs().amax(dim=1) > 0
                if not torch.any(busy):
                    continue
                keep = [t for t, b in zip(tiles, busy.tolist(), strict=True) if b]
                spectrum = torch.fft.rfft2(blocks[busy], s=keep[0].fft) * self._node_patches(j, keep)
                results = torch.fft.irfft2(spectrum.sum(1), s=keep[0].fft)
                for tile, result in zip(keep, results, strict=True):
                    r0, r1, c0, c1 = tile.box
                    _add_clipped(target, result[: r1 - r0 + h - 1, : c1 - c0 + w - 1], tile.out)
            if progress:
                progress("forward: nodes", j + 1, J)
        return image if per_lenslet else image[0]

    # -- adjoint ----------------------------------------------------------------------------
    def adjoint(self, image, *, progress: Progress | None = None):
        """Adjoint of :meth:`forward` (not per lenslet): volume (z, y, x) from an image (y, x),
        or (B, z, y, x) from (B, y, x)."""
        batch, single, is_numpy = self._as_batch(image, 2)
        if tuple(batch.shape[1:]) != tuple(self.sensor_shape):
            raise ValueError(f"image shape {tuple(batch.shape[1:])} does not match the sensor {self.sensor_shape}")
        out = torch.stack([self._adjoint_one(y, progress) for y in batch])
        out = out[0] if single else out
        return out.cpu().numpy() if is_numpy else out

    @torch.no_grad()
    def _adjoint_one(self, image: torch.Tensor, progress: Progress | None) -> torch.Tensor:
        J = self.n_lenslets
        Hc, Wc = self.canvas_shape
        h, w = self.model.patch_shape
        n_nodes = len(self.depth_nodes)
        spectra = torch.zeros((J, n_nodes, Hc, Wc // 2 + 1), dtype=torch.complex64, device=self.device)
        for j in range(J):
            canvases = {g: torch.zeros((Hc, Wc), dtype=torch.float32, device=self.device) for g in self.depth_nodes}
            for tiles in self._chunks(j):
                rh = max(t.box[1] - t.box[0] for t in tiles) + h - 1
                rw = max(t.box[3] - t.box[2] for t in tiles) + w - 1
                regions = torch.zeros((len(tiles), rh, rw), dtype=torch.float32, device=self.device)
                for i, tile in enumerate(tiles):
                    r0, r1, c0, c1 = tile.box
                    regions[i, : r1 - r0 + h - 1, : c1 - c0 + w - 1] = _take_clipped(
                        image, tile.out, (r1 - r0 + h - 1, c1 - c0 + w - 1)
                    )
                busy = regions.reshape(len(tiles), -1).abs().amax(dim=1) > 0
                if not torch.any(busy):
                    continue
                keep = [t for t, b in zip(tiles, busy.tolist(), strict=True) if b]
                spectrum = torch.fft.rfft2(regions[busy], s=keep[0].fft)[:, None] * torch.conj(
                    self._node_patches(j, keep)
                )
                blocks = torch.fft.irfft2(spectrum, s=keep[0].fft)
                for tile, block in zip(keep, blocks, strict=True):
                    r0, r1, c0, c1 = tile.box
                    for k, (g, weight) in enumerate(zip(tile.depth_nodes, tile.weights, strict=True)):
                        canvases[g][r0:r1, c0:c1] += self._weighted(block[k, : r1 - r0, : c1 - c0], weight)
            for g in self.depth_nodes:
                spectra[j, self._slot[g]] = torch.fft.rfft2(canvases[g])
            if progress:
                progress("adjoint: nodes", j + 1, J)
        nz, ny, nx = self.grid.shape
        volume = torch.zeros((nz, ny, nx), dtype=torch.float32, device=self.device)
        Hp, Wp = self.plane_shape
        for z in range(nz):
            total = torch.zeros((Hc, Wc // 2 + 1), dtype=torch.complex64, device=self.device)
            mixed = torch.empty_like(total)
            for j in range(J):
                (g, a), *rest = self.depth_weights[z]
                torch.mul(spectra[j, self._slot[g]], a, out=mixed)
                for g, a in rest:
                    mixed.add_(spectra[j, self._slot[g]], alpha=a)
                mixed.mul_(self._kx_conj[z, j][None, :])
                total.addcmul_(mixed, self._ky_conj[z, j][:, None])
            plane = torch.fft.irfft2(total, s=(Hc, Wc))[:Hp, :Wp]
            volume[z] = self._gather(plane, z)
            if progress:
                progress("adjoint: shear", z + 1, nz)
        return volume


def _tent(u: np.ndarray, g: int) -> np.ndarray:
    return np.clip(1.0 - np.abs(u - g), 0.0, None)


def _splat_axis(data: torch.Tensor, axis: _Axis) -> torch.Tensor:
    """Splat the rows of ``data`` (n_in, m) onto ``axis.n_out`` rows."""
    if axis.matrix is not None:
        return torch.sparse.mm(axis.matrix, data.contiguous())
    out = torch.zeros((axis.n_out, data.shape[1]), dtype=data.dtype, device=data.device)
    n = axis.n_in
    if axis.step == 1:
        out[axis.start : axis.start + n] = data
    else:
        out[axis.start - n + 1 : axis.start + 1] = data.flip(0)
    return out


def _gather_axis(data: torch.Tensor, axis: _Axis) -> torch.Tensor:
    """Transpose of :func:`_splat_axis`: (n_out, m) → (n_in, m)."""
    if axis.transpose is not None:
        return torch.sparse.mm(axis.transpose, data.contiguous())
    n = axis.n_in
    if axis.step == 1:
        return data[axis.start : axis.start + n]
    return data[axis.start - n + 1 : axis.start + 1].flip(0)


def _add_clipped(target: torch.Tensor, block: torch.Tensor, origin: tuple[int, int]) -> None:
    H, W = target.shape
    r, c = origin
    rs, re = max(r, 0), min(r + block.shape[0], H)
    cs, ce = max(c, 0), min(c + block.shape[1], W)
    if rs < re and cs < ce:
        target[rs:re, cs:ce] += block[rs - r : re - r, cs - c : ce - c]


def _take_clipped(image: torch.Tensor, origin: tuple[int, int], shape: tuple[int, int]) -> torch.Tensor:
    out = torch.zeros(shape, dtype=image.dtype, device=image.device)
    H, W = image.shape
    r, c = origin
    rs, re = max(r, 0), min(r + shape[0], H)
    cs, ce = max(c, 0), min(c + shape[1], W)
    if rs < re and cs < ce:
        out[rs - r : re - r, cs - c : ce - c] = image[rs:re, cs:ce]
    return out


#: Voxels per chunk of the on-the-fly bilinear splat (bounds its index arrays to ≈ 100 MB).
SPLAT_CHUNK_ELEMENTS = 2**21


def _affine_bilinear(affine: np.ndarray, shape: tuple[int, int], width: int, device: torch.device):
    """Bilinear splat of a (ny, nx) plane through ``affine`` (see :class:`_Splat`) onto a plane
    ``width`` px wide, chunk by chunk of rows: yields ``(rows, index, weights)`` with ``rows`` a
    slice of the input rows and, for the four corners, the flat output indices (int64) and the
    float32 weights of every input voxel of the chunk (computed in float64)."""
    ny, nx = shape
    ix = torch.arange(nx, dtype=torch.float64, device=device) - (nx - 1) / 2.0
    step = max(1, SPLAT_CHUNK_ELEMENTS // max(nx, 1))
    for start in range(0, ny, step):
        stop = min(start + step, ny)
        iy = torch.arange(start, stop, dtype=torch.float64, device=device)[:, None] - (ny - 1) / 2.0
        rows = affine[0, 0] * iy + affine[0, 1] * ix + affine[0, 2]
        cols = affine[1, 0] * iy + affine[1, 1] * ix + affine[1, 2]
        r0, c0 = torch.floor(rows), torch.floor(cols)
        tr, tc = (rows - r0).reshape(-1), (cols - c0).reshape(-1)
        base = (r0.long() * width + c0.long()).reshape(-1)
        index = (base, base + 1, base + width, base + width + 1)
        weights = tuple(w.to(torch.float32) for w in ((1 - tr) * (1 - tc), (1 - tr) * tc, tr * (1 - tc), tr * tc))
        yield slice(start, stop), index, weights
