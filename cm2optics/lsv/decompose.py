"""Truncated SVD of the registered focus arrays into basis PSFs and coefficients.

The N crops of a scan, each a stack of J registered foci (h × w), are the rows of
``X`` (N × J·h·w). With ``X = U·S·Vᵀ``, the first K rows of ``Vᵀ`` are the basis PSFs (each a
3×3 focus array) and ``U_K·S_K`` the coefficients of every calibration position. The SVD goes
through the N × N Gram matrix ``X·Xᵀ`` in float64 (N is at most a few thousand; the pixels are
hundreds of thousands), so memory stays at a few copies of ``X`` in float32. Crops too large
for memory (a dense full-field scan) stay on disk (:mod:`cm2optics.lsv.crop_store`) and are
decomposed by a randomized SVD in a few passes over them, a chunk of positions at a time.

Error against K, two ways, both on the calibration set:

- ``nmse``: ``‖X − X_K‖²_F / ‖X‖²_F``, the share of the scan's energy the K terms miss (the
  paper's "approximation error on the calibration set", K = 64 → ≈ 0.025);
- ``nmse_per_psf``: the mean over positions of ``‖x_n − x̂_n‖² / ‖x_n‖²`` (dark positions left
  out), which weighs dim PSFs as much as bright ones.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from cm2optics.lsv.crop_store import CropStore, position_chunks

Progress = Callable[[str, int, int], None]

__all__ = [
    "Decomposition",
    "decompose",
    "basis_gram",
    "decompose_per_lenslet",
    "gram",
    "lenslet_bases",
    "numerical_rank",
    "lenslet_blocks",
    "products",
    "project",
    "streamed_decompose",
    "trim_window",
]


@dataclass(frozen=True)
class Decomposition:
    """basis: (K, J, h, w) float32, orthonormal; coefficients: (N, K) float32;
    singular_values: (min(N, D),) all of them; nmse, nmse_per_psf: (len(singular_values) + 1,)
    errors keeping 0, 1, … terms."""

    basis: np.ndarray
    coefficients: np.ndarray
    singular_values: np.ndarray
    nmse: np.ndarray
    nmse_per_psf: np.ndarray

    @property
    def rank(self) -> int:
        return len(self.basis)


def gram(X: np.ndarray, chunk: int = 16384) -> np.ndarray:
    """X·Xᵀ in float64, accumulated over column chunks of the (N, D) float32 matrix."""
    N = X.shape[0]
    G = np.zeros((N, N))
    for start in range(0, X.shape[1], chunk):
        block = X[:, start : start + chunk].astype(np.float64)
        G += block @ block.T
    return G


def decompose(crops: np.ndarray | CropStore, rank: int, progress: Progress | None = None) -> Decomposition:
    """Truncated SVD of ``crops`` (N, J, h, w) keeping ``rank`` terms (capped at N): exact through
    the Gram matrix for crops in memory, randomized (:func:`streamed_decompose`) for a
    :class:`~cm2optics.lsv.crop_store.CropStore` on disk."""
    if not isinstance(crops, np.ndarray):
        return streamed_decompose(crops, rank, progress=progress)
    X = crops.reshape(crops.shape[0], -1)
    singular, vectors, norms = _gram_svd(X)
    K = _kept_rank(singular, rank, len(X))
    basis = _right_vectors(X, singular[:K], vectors[:, :K])
    return _decomposition(basis.reshape((K,) + crops.shape[1:]), vectors * singular, singular, norms)


def decompose_per_lenslet(crops: np.ndarray | CropStore, rank: int, progress: Progress | None = None) -> Decomposition:
    """Each lenslet its own truncated SVD of its foci ``crops[:, j]`` (exact, through its Gram
    matrix), ``rank`` terms per lenslet, as one orthonormal basis of J·rank focus arrays each dark
    but in its own lenslet (block-diagonal: lenslet bases on disjoint supports are orthogonal to
    each other), ordered by singular value over all lenslets, so that a truncation keeps the
    strongest terms. Errors against the number of terms kept are those of this ordering. A
    lenslet whose foci span fewer than ``rank`` dimensions keeps fewer terms."""
    N, J = crops.shape[:2]
    lenslet_of, singular, coefficients, blocks = [], [], [], []
    norms = np.zeros(N)
    for j, (block, s, c, n) in enumerate(_lenslet_svds(crops, rank, progress)):
        blocks.append(block)
        lenslet_of.append(np.full(len(s), j))
        singular.append(s)
        coefficients.append(c)
        norms += n
    kept = [len(b) for b in blocks]
    term = np.concatenate([np.arange(len(s)) for s in singular])
    lenslet_of, singular = np.concatenate(lenslet_of), np.concatenate(singular)
    order = np.argsort(-singular, kind="stable")
    order = order[term[order] < np.asarray(kept)[lenslet_of[order]]]  # the kept terms first …
    rest = np.setdiff1d(np.arange(len(singular)), order)
    order = np.concatenate([order, rest[np.argsort(-singular[rest], kind="stable")]])  # … then the others
    basis = np.zeros((sum(kept), J) + crops.shape[2:], np.float32)
    for i, (j, k) in enumerate(zip(lenslet_of[order[: len(basis)]], term[order[: len(basis)]], strict=True)):
        basis[i, j] = blocks[j][k].reshape(crops.shape[2:])
    all_coefficients = np.concatenate(coefficients, axis=1)[:, order]
    return _decomposition(basis, all_coefficients, singular[order], norms)


def _lenslet_svds(
    crops: np.ndarray | CropStore, rank: int, progress: Progress | None
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per lenslet j of ``crops`` (N, J, h, w): its kept right singular vectors (K_j, h·w) float64,
    all its singular values (N,), its coefficients (N, N) and its crops' squared norms (N,)."""
    N, J = crops.shape[:2]
    for j in range(J):
        X = np.asarray(crops[:, j : j + 1]).reshape(N, -1)
        s, vectors, n = _gram_svd(X)
        K = _kept_rank(s, rank, N)
        yield _right_vectors(X, s[:K], vectors[:, :K]), s, vectors * s, n
        if progress:
            progress("per-lenslet SVD (lenslets)", j + 1, J)


def lenslet_bases(crops: np.ndarray | CropStore, rank: int, progress: Progress | None = None) -> list[np.ndarray]:
    """Each lenslet's own orthonormal basis (K_j, h, w) float32 of its foci ``crops[:, j]`` (N, J,
    h, w): the blocks of :func:`decompose_per_lenslet` kept apart (J·K·h·w numbers, not J²·K·h·w),
    ``rank`` terms each at most, in the order of their singular values."""
    shape = crops.shape[2:]
    return [
        block.reshape((len(block),) + shape).astype(np.float32) for block, *_ in _lenslet_svds(crops, rank, progress)
    ]


def _gram_svd(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Singular values (descending, N), left singular vectors (N, N) and squared row norms (N,)
    of ``X`` (N, D) through its Gram matrix in float64."""
    if not np.all(np.isfinite(X)):
        raise ValueError("the focus crops contain NaN or infinite values")
    G = gram(X)
    eigenvalues, vectors = np.linalg.eigh(G)
    order = np.argsort(eigenvalues)[::-1]
    return np.sqrt(np.clip(eigenvalues[order], 0, None)), vectors[:, order], np.diag(G).copy()


def _right_vectors(X: np.ndarray, singular: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """(K, D) right singular vectors ``Σ⁻¹ Uᵀ X`` of ``X`` (N, D) for the K singular values and
    left vectors (N, K) given (zero where a singular value is 0), float64 over column chunks."""
    scale = np.where(singular > 0, 1.0 / np.maximum(singular, 1e-300), 0.0)
    projector = (vectors * scale).T  # (K, N)
    basis = np.zeros((len(singular), X.shape[1]), np.float64)
    for start in range(0, X.shape[1], 16384):
        basis[:, start : start + 16384] = projector @ X[:, start : start + 16384].astype(np.float64)
    return basis


#: Columns (pixels) of a basis converted to float64 at a time: a large basis (a per-lenslet one at
#: K = 128 is 1152 focus arrays) is never held whole in float64.
COLUMN_CHUNK = 16384


def lenslet_blocks(basis: np.ndarray) -> list[np.ndarray] | None:
    """For a basis (K, J, h, w) whose every term has light in one lenslet at most (a per-lenslet
    basis, :func:`decompose_per_lenslet`), the term indices of each lenslet; else None."""
    K, J = basis.shape[:2]
    lit = np.stack([np.abs(basis[:, j]).reshape(K, -1).max(axis=1) > 0 for j in range(J)], axis=1)
    if J == 1 or (lit.sum(axis=1) > 1).any():
        return None
    return [np.flatnonzero(lit[:, j]) for j in range(J)]


def _dense_products(X: np.ndarray, basis: np.ndarray) -> np.ndarray:
    out = np.zeros((len(X), len(basis)))
    for start in range(0, basis.shape[1], COLUMN_CHUNK):
        columns = slice(start, start + COLUMN_CHUNK)
        out += X[:, columns].astype(np.float64) @ basis[:, columns].astype(np.float64).T
    return out


def products(X: np.ndarray, basis: np.ndarray, blocks: list[np.ndarray] | None = None) -> np.ndarray:
    """``X · Bᵀ`` (n, K) in float64 of rows ``X`` (n, J, h, w) and a basis ``B`` (K, J, h, w),
    accumulated over column chunks so that neither is converted to float64 whole; with ``blocks``
    (:func:`lenslet_blocks`) lenslet by lenslet, skipping the products with dark lenslets."""
    if blocks is None:
        return _dense_products(X.reshape(len(X), -1), basis.reshape(len(basis), -1))
    out = np.zeros((len(X), len(basis)))
    for j, terms in enumerate(blocks):
        if len(terms):
            out[:, terms] = _dense_products(X[:, j].reshape(len(X), -1), basis[terms, j].reshape(len(terms), -1))
    return out


def basis_gram(basis: np.ndarray, blocks: list[np.ndarray] | None = None) -> np.ndarray:
    """``B · Bᵀ`` (K, K) in float64 of a basis (K, J, h, w); with ``blocks`` block by block."""
    if blocks is None:
        return gram(basis.reshape(len(basis), -1))
    G = np.zeros((len(basis), len(basis)))
    for j, terms in enumerate(blocks):
        if len(terms):
            G[np.ix_(terms, terms)] = gram(basis[terms, j].reshape(len(terms), -1))
    return G


def project(crops: np.ndarray | CropStore, basis: np.ndarray) -> np.ndarray:
    """(N, K) coefficients of ``crops`` (N, J, h, w) on an orthonormal ``basis`` (K, J, h, w), in float64 sums."""
    blocks = lenslet_blocks(basis)
    coefficients = np.zeros((len(crops), len(basis)))
    for first, block in position_chunks(crops):
        for start in range(0, len(block), 64):
            rows = block[start : start + 64]
            coefficients[first + start : first + start + len(rows)] = products(rows, basis, blocks)
    return coefficients.astype(np.float32)


def _kept_rank(singular: np.ndarray, rank: int, N: int) -> int:
    """K: ``rank`` capped at N and at the singular values above 10⁻⁷ of the largest (at least 1)."""
    K = int(min(rank, N, int(np.sum(singular > singular[0] * 1e-7)) if singular[0] > 0 else 1))
    return max(K, 1)


def _decomposition(
    basis: np.ndarray, coefficients: np.ndarray, singular: np.ndarray, norms: np.ndarray
) -> Decomposition:
    """The decomposition from the kept ``basis`` (K, J, h, w), the coefficients of every computed
    term (N, L), their singular values (L,) and each crop's squared norm (N,), with the errors
    against the number of terms kept (0 … L) of the whole set and per PSF."""
    K, N = len(basis), len(norms)
    total = float(norms.sum())
    captured = np.concatenate([[0.0], np.cumsum(singular**2)])
    nmse = 1.0 - captured / total if total > 0 else np.zeros_like(captured)
    cumulative = np.concatenate([np.zeros((N, 1)), np.cumsum(coefficients**2, axis=1)], axis=1)
    valid = norms > 1e-12 * max(norms.max(), 1e-300)
    per_psf = 1.0 - cumulative[valid] / norms[valid, None]
    nmse_per_psf = np.clip(per_psf, 0, None).mean(axis=0) if valid.any() else np.zeros(len(captured))
    return Decomposition(
        basis=basis.astype(np.float32, copy=False),
        coefficients=coefficients[:, :K].astype(np.float32),
        singular_values=singular,
        nmse=np.clip(nmse, 0, None),
        nmse_per_psf=nmse_per_psf,
    )


#: The streamed SVD samples the crops' range with K + max(K, 16) random vectors and refines it
#: with this many power iterations (Halko, Martinsson & Tropp 2011, algorithm 4.4): the leading K
#: terms then match the exact SVD's closely even where the spectrum decays slowly.
POWER_ITERATIONS = 2


def streamed_decompose(
    crops: CropStore,
    rank: int,
    *,
    power_iterations: int = POWER_ITERATIONS,
    seed: int = 0,
    progress: Progress | None = None,
) -> Decomposition:
    """Randomized truncated SVD of crops read a chunk of positions at a time: ``2 + 2·q`` passes
    over them (q power iterations), memory O((N + D)·L) for L = K + max(K, 16) sampled terms
    instead of the N × D crops. Singular values and errors are those of the L terms (the exact
    SVD's tail beyond them is not computed)."""
    N, shape = len(crops), crops.shape[1:]
    D = int(np.prod(shape))
    L = int(min(N, rank + max(rank, 16)))
    passes = _Passes(crops, 2 + 2 * power_iterations, progress)
    norms = np.zeros(N)
    Y = np.zeros((N, L))
    omega = np.random.default_rng(seed).standard_normal((D, L)).astype(np.float32)
    for rows, X in passes.chunks():
        if not np.all(np.isfinite(X)):
            raise ValueError("the focus crops contain NaN or infinite values")
        norms[rows] = np.einsum("np,np->n", X, X, dtype=np.float64)
        Y[rows] = X @ omega
    del omega
    Q = np.linalg.qr(Y)[0]
    for _ in range(power_iterations):
        Z = np.linalg.qr(passes.transposed_product(Q))[0]  # (D, L): the row space
        Q = np.linalg.qr(passes.product(Z))[0]
    Bt = passes.transposed_product(Q)  # (D, L) = Xᵀ Q, B = Qᵀ X
    eigenvalues, U = np.linalg.eigh(Bt.T @ Bt)
    order = np.argsort(eigenvalues)[::-1]
    singular = np.sqrt(np.clip(eigenvalues[order], 0, None))
    U = U[:, order]
    K = _kept_rank(singular, rank, N)
    basis = (Bt @ U[:, :K]) / np.maximum(singular[:K], 1e-300)  # (D, K): right singular vectors
    return _decomposition(basis.T.reshape((K,) + shape), Q @ (U * singular), singular, norms)


class _Passes:
    """Passes over crops on disk as (positions, D) float32 chunks, ``total`` of them reported to ``progress``."""

    def __init__(self, crops: CropStore, total: int, progress: Progress | None) -> None:
        self.crops, self.progress = crops, progress
        self.total = total * -(-len(crops) // crops.chunk)
        self.done = 0

    def chunks(self) -> Iterator[tuple[slice, np.ndarray]]:
        """(rows of the chunk's positions, their crops flattened) for one pass."""
        for start, block in position_chunks(self.crops):
            yield slice(start, start + len(block)), block.reshape(len(block), -1)
            self.done += 1
            if self.progress:
                self.progress("streamed SVD (chunks read)", self.done, self.total)

    def product(self, M: np.ndarray) -> np.ndarray:
        """X·M (N, L) of the crops X (N, D) and M (D, L), float64, one pass."""
        out = np.zeros((len(self.crops), M.shape[1]))
        M32 = M.astype(np.float32)
        for rows, X in self.chunks():
            out[rows] = X @ M32
        return out

    def transposed_product(self, M: np.ndarray) -> np.ndarray:
        """Xᵀ·M (D, L) of the crops X (N, D) and M (N, L), float64 sums over the chunks, one pass."""
        out = np.zeros((int(np.prod(self.crops.shape[1:])), M.shape[1]))
        for rows, X in self.chunks():
            out += X.T @ M[rows].astype(np.float32)
        return out


def numerical_rank(singular_values: np.ndarray, tolerance: float = 1e-4) -> int:
    """Number of singular values above ``tolerance`` × the largest."""
    s = np.asarray(singular_values)
    return int(np.sum(s > tolerance * s[0])) if len(s) and s[0] > 0 else 0


def trim_window(basis: np.ndarray, singular_values: np.ndarray, tolerance: float = 1e-6) -> tuple[slice, slice]:
    """The smallest window, centred on the crops' centre pixel (h//2, w//2) and of even size,
    outside which the calibration PSFs (basis weighted by the singular values) hold at most
    ``tolerance`` of their energy. The crops are cut generously (160 px at full resolution);
    their dark margins cost time in every convolution and carry nothing."""
    K, J, h, w = basis.shape
    weights = np.asarray(singular_values[:K], float) ** 2
    energy = np.einsum("k,kjab->ab", weights, basis.astype(np.float64) ** 2)
    total = energy.sum()
    cy, cx = h // 2, w // 2
    if total <= 0:
        return slice(0, h), slice(0, w)
    rows = energy.sum(axis=1)
    cols = energy.sum(axis=0)

    def half_width(profile: np.ndarray, centre: int, size: int) -> int:
        for r in range(1, max(centre, size - centre) + 1):
            inside = profile[max(centre - r, 0) : min(centre + r, size)].sum()
            if total - inside <= 0.5 * tolerance * total:
                return r
        return max(centre, size - centre)

    ry = half_width(rows, cy, h)
    rx = half_width(cols, cx, w)
    return slice(max(cy - ry, 0), min(cy + ry, h)), slice(max(cx - rx, 0), min(cx + rx, w))
