"""Truncated SVD of the registered focus arrays into basis PSFs and coefficients.

The N crops of a scan, each a stack of J registered foci (h × w), are the rows of
``X`` (N × J·h·w). With ``X = U·S·Vᵀ``, the first K rows of ``Vᵀ`` are the basis PSFs (each a
3×3 focus array) and ``U_K·S_K`` the coefficients of every calibration position. The SVD goes
through the N × N Gram matrix ``X·Xᵀ`` in float64 (N is at most a few thousand; the pixels are
hundreds of thousands), so memory stays at a few copies of ``X`` in float32.

Error against K, two ways, both on the calibration set:

- ``nmse``: ``‖X − X_K‖²_F / ‖X‖²_F``, the share of the scan's energy the K terms miss (the
  paper's "approximation error on the calibration set", K = 64 → ≈ 0.025);
- ``nmse_per_psf``: the mean over positions of ``‖x_n − x̂_n‖² / ‖x_n‖²`` (dark positions left
  out), which weighs dim PSFs as much as bright ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Decomposition", "decompose", "numerical_rank", "trim_window"]


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


def decompose(crops: np.ndarray, rank: int) -> Decomposition:
    """Truncated SVD of ``crops`` (N, J, h, w) keeping ``rank`` terms (capped at N)."""
    N = crops.shape[0]
    shape = crops.shape[1:]
    X = crops.reshape(N, -1)
    if not np.all(np.isfinite(X)):
        raise ValueError("the focus crops contain NaN or infinite values")
    G = gram(X)
    eigenvalues, vectors = np.linalg.eigh(G)
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues = np.clip(eigenvalues[order], 0, None)
    vectors = vectors[:, order]
    singular = np.sqrt(eigenvalues)
    K = int(min(rank, N, int(np.sum(singular > singular[0] * 1e-7)) if singular[0] > 0 else 1))
    K = max(K, 1)
    scale = np.where(singular[:K] > 0, 1.0 / np.maximum(singular[:K], 1e-300), 0.0)
    projector = (vectors[:, :K] * scale).T  # (K, N)
    basis = np.zeros((K, X.shape[1]), np.float64)
    for start in range(0, X.shape[1], 16384):
        basis[:, start : start + 16384] = projector @ X[:, start : start + 16384].astype(np.float64)
    coefficients = vectors[:, :K] * singular[:K]  # (N, K)
    total = float(eigenvalues.sum())
    captured = np.concatenate([[0.0], np.cumsum(eigenvalues)])
    nmse = 1.0 - captured / total if total > 0 else np.zeros_like(captured)
    norms = np.diag(G)
    full_coefficients = vectors * singular  # (N, N)
    cumulative = np.concatenate([np.zeros((N, 1)), np.cumsum(full_coefficients**2, axis=1)], axis=1)
    valid = norms > 1e-12 * max(norms.max(), 1e-300)
    per_psf = 1.0 - cumulative[valid] / norms[valid, None]
    nmse_per_psf = np.clip(per_psf, 0, None).mean(axis=0) if valid.any() else np.zeros(N + 1)
    return Decomposition(
        basis=basis.reshape((K,) + shape).astype(np.float32),
        coefficients=coefficients.astype(np.float32),
        singular_values=singular,
        nmse=np.clip(nmse, 0, None),
        nmse_per_psf=nmse_per_psf,
    )


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
