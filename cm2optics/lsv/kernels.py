"""Sub-pixel shifts with the Keys cubic kernel (a = −½), in numpy, shared by the crop
extraction and the operators.

A shift by ``s = n + ε`` (``n`` integer, ``0 ≤ ε < 1``) moves a sampled signal by ``s`` pixels:
``out[u] = Σ_t w_t(ε)·in[u − n − t]`` over the four taps ``t = −1, 0, 1, 2`` with
``w_t(ε) = keys(t − ε)``. It is exact for integer shifts (``ε = 0`` gives a delta), keeps the
sum of the signal (the weights sum to 1) and reproduces linear ramps. Sampling a signal at
the continuous position ``n + ε`` uses the same weights: ``f(n + ε) = Σ_t w_t(ε)·f[n + t]``.
"""

from __future__ import annotations

import numpy as np

TAPS = np.array([-1, 0, 1, 2])


def keys(s: np.ndarray, a: float = -0.5) -> np.ndarray:
    """The Keys cubic convolution kernel at ``s`` (pixels)."""
    s = np.abs(np.asarray(s, dtype=np.float64))
    out = np.zeros_like(s)
    inner = s <= 1
    outer = (s > 1) & (s < 2)
    out[inner] = (a + 2) * s[inner] ** 3 - (a + 3) * s[inner] ** 2 + 1
    out[outer] = a * s[outer] ** 3 - 5 * a * s[outer] ** 2 + 8 * a * s[outer] - 4 * a
    return out


def split_shift(shift: np.ndarray, snap: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Integer part ``n`` and fraction ``ε`` of ``shift`` (pixels); fractions within ``snap`` of
    an integer are snapped to it, so that nearly-integer shifts are exact."""
    shift = np.asarray(shift, dtype=np.float64)
    rounded = np.round(shift)
    shift = np.where(np.abs(shift - rounded) < snap, rounded, shift)
    n = np.floor(shift)
    return n.astype(np.int64), shift - n


def shift_weights(eps: np.ndarray) -> np.ndarray:
    """Tap weights (..., 4) for fractions ``eps`` (...,), taps ``t = −1, 0, 1, 2``."""
    eps = np.asarray(eps, dtype=np.float64)
    return keys(TAPS - eps[..., None])


def shift_kernel_dft(shift: np.ndarray, n_fft: int, real: bool) -> np.ndarray:
    """DFT (length ``n_fft``, or ``n_fft//2 + 1`` if ``real``) of the 1-D shift kernels for
    ``shift`` (...,) pixels: a complex128 array (..., n_freq). The kernel is placed at indices
    ``(n + t) mod n_fft``, so multiplying a zero-padded signal's DFT by it shifts the signal
    exactly as :func:`apply_shift_1d` does when nothing wraps around."""
    n, eps = split_shift(shift)
    weights = shift_weights(eps)  # (..., 4)
    freqs = np.fft.rfftfreq(n_fft) if real else np.fft.fftfreq(n_fft)
    positions = n[..., None] + TAPS  # (..., 4)
    phase = np.exp(-2j * np.pi * positions[..., None] * freqs)  # (..., 4, n_freq)
    return np.einsum("...t,...tf->...f", weights, phase)


def sample_window(image: np.ndarray, centre: tuple[float, float], shape: tuple[int, int]) -> np.ndarray:
    """A ``shape`` window of ``image`` whose pixel ``(h//2, w//2)`` samples the continuous
    position ``centre`` (row, col), by separable Keys interpolation; zero outside the image."""
    h, w = shape
    out_rows = _sample_axis_indices(centre[0], h)
    out_cols = _sample_axis_indices(centre[1], w)
    rows, wr = out_rows
    cols, wc = out_cols
    padded = np.zeros((len(rows), len(cols)), dtype=np.float64)
    rv = (rows >= 0) & (rows < image.shape[0])
    cv = (cols >= 0) & (cols < image.shape[1])
    padded[np.ix_(rv, cv)] = image[np.ix_(rows[rv], cols[cv])]
    # rows: output a uses padded rows a .. a+3 with weights wr
    tmp = sum(wr[t] * padded[t : t + h] for t in range(4))
    return sum(wc[t] * tmp[:, t : t + w] for t in range(4))


def _sample_axis_indices(centre: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    n, eps = split_shift(np.asarray(centre))
    start = int(n) - size // 2 - 1
    return np.arange(start, start + size + 3), shift_weights(eps)


def apply_shift_1d(signal: np.ndarray, shift: float, axis: int = -1) -> np.ndarray:
    """Shift ``signal`` by ``shift`` pixels along ``axis`` (the output is 3 samples longer plus
    the integer shift is applied by index: out[u] for u in [0, len + n + 3)); for tests."""
    n, eps = split_shift(np.asarray(shift))
    weights = shift_weights(eps)
    signal = np.moveaxis(np.asarray(signal, dtype=np.float64), axis, -1)
    length = signal.shape[-1]
    out = np.zeros(signal.shape[:-1] + (length + int(n) + 3,))
    for t, weight in zip(TAPS, weights, strict=True):
        start = int(n) + t
        if start < 0:
            raise ValueError("apply_shift_1d supports shifts ≥ 1 only")
        out[..., start : start + length] += weight * signal
    return np.moveaxis(out, -1, axis)
