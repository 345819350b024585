"""Diffraction: from traced rays to the PSF of one lenslet, one band, one source.

Method (a ray-traced wavefront on the reference sphere, propagated by the Debye–Wolf integral,
evaluated as an FFT; a geometric branch takes over where aberrations are many waves):

1. **Reference sphere.** Each lenslet's sphere is centred on a reference point r_ref of the sensor
   plane (the power centroid of its rays) and passes through the centre of its paraxial exit
   pupil (the lenslet's vertex, the stop, seen through the PMMA and the film). Every ray is
   followed back from the sensor plane along its last segment (in air) to the sphere, at q; W is
   the optical path from the source to q (the wavefront on the sphere) and (L, M) are the x and y
   components of the unit vector from q to r_ref.
2. **Pupil mapping.** A coarse grid of rays (``coarse``² per lenslet and band) gives a bivariate
   Legendre polynomial (degree :data:`MAP_DEGREE`) from (L, M) back to the launch tangents (u, v)
   of the rays leaving the source; a square grid in (L, M), spacing ΔL, over the rays that pass,
   is then traced exactly through it (the map is nearly linear: it lands within 10⁻⁴ ΔL).
3. **Debye–Wolf integral.** The field on the sensor plane is the superposition of the plane waves
   leaving the sphere towards its centre,

       U(x, y) = (1/λ) ∬ A(L, M) e^{ik W} e^{ik [L (x − x_ref) + M (y − y_ref)]} dL dM,

   with ΔL = λ / (N h) a zero-padded inverse FFT whose output pitch is exactly h
   (:func:`debye_fft`); a phase ramp on the pupil puts the output grid on the pixels'
   sub-samples. (:func:`mft`, a matrix Fourier transform, evaluates the same sum on any grid.)
   Because the samples sit where the rays really cross the sphere (not where a linear map of the
   entrance pupil would put them), pupil aberration and the tilted, anamorphic cones of the
   off-axis lenslets are exact; the phase carries every aberration of the exact trace. With a
   linear pupil map and uniform amplitude the same sum is the classical FFT PSF of optical
   design codes (see :mod:`.crosscheck`, which checks both against Optiland).
4. **Amplitude.** |A|² is the power per unit dL dM: the source's radiant intensity
   (:class:`~.source.AngularProfile`) × the solid angle per unit (u, v), (1 + u² + v²)^(−3/2),
   × the Jacobian |∂(u, v)/∂(L, M)| (from the traced grid) × the lens's Fresnel transmittance ×
   the band's spectral weight at the ray's angles on the filter and the film (:mod:`.spectral`);
   0 where the ray is blocked. Then ∬ |U|² dx dy is the power that reaches the sensor
   (Parseval): the PSF is in photons detected per photon emitted.
5. **Sampling.** The FFT period λ/ΔL is at least :data:`PERIOD_FACTOR` × the output window (the
   rays' geometric spot plus a diffraction margin), so the spot does not alias onto itself, and
   at least :data:`MIN_SAMPLES` pupil samples span the passed rays.
6. **Geometric branch.** Where the RMS wavefront error of a lenslet's rays exceeds a threshold
   (several waves: far off axis), diffraction changes the spot by a fraction of its size and a
   faithful Debye sum would need ≈ 10⁵ pupil samples; there the irradiance is the density of a
   uniform launch grid of rays, blurred by a Gaussian of the aperture's diffraction core
   (σ = 0.42 λ / 2NA'), see :meth:`~.psf.EmissionModel._finish_geometric`.

Valid while the Fresnel number of the converging beam is large (here ≈ 90) and the sensor lies
in the last medium (it does: air). Scalar: no polarisation in the focus (NA' ≈ 0.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
from numpy.polynomial.legendre import legvander

__all__ = [
    "MAP_DEGREE",
    "MIN_SAMPLES",
    "PERIOD_FACTOR",
    "PupilMap",
    "debye_fft",
    "fft_size",
    "fit_pupil_map",
    "mft",
    "solve_least_squares",
]

#: Degree of the bivariate polynomial (L, M) → (u, v).
MAP_DEGREE = 8
#: Fewest pupil samples across the passed rays along the wider axis.
MIN_SAMPLES = 48
#: FFT period over output window: the spot must not alias onto itself.
PERIOD_FACTOR = 1.25
#: Largest FFT side.
MAX_FFT = 4096


def _powers(degree: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def solve_least_squares(basis: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Least squares by normal equations summed without BLAS (``einsum``): for the small, well
    conditioned (orthogonal-polynomial) problems here this is exact enough and avoids
    multi-threaded BLAS, which costs tens of ms per call on a busy machine."""
    gram = np.einsum("ni,nj->ij", basis, basis)
    rhs = np.einsum("ni,n...->i...", basis, values)
    gram[np.diag_indices_from(gram)] *= 1.0 + 1e-12
    return np.linalg.solve(gram, rhs)


@dataclass(frozen=True, eq=False)
class PupilMap:
    """A fitted map from final direction cosines (L, M) to launch tangents (u, v).

    centre, scale: (L0, M0) and (Ls, Ms): the polynomial's variables are a = (L − L0)/Ls and
    b = (M − M0)/Ms, both within [−1, 1] over the fitted rays.
    coef_u, coef_v: (d+1, d+1) coefficients of the Legendre products P_i(a)·P_j(b), i + j ≤ d.
    degree: total degree d. residual: RMS of the fit over the fitted rays (tangent units).
    """

    centre: tuple[float, float]
    scale: tuple[float, float]
    coef_u: np.ndarray
    coef_v: np.ndarray
    degree: int
    residual: float

    def grid(self, l_axis: np.ndarray, m_axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) on the grid ``m_axis`` × ``l_axis``, arrays of shape (n_m, n_l) (separable)."""
        pa = legvander((np.asarray(l_axis, dtype=float) - self.centre[0]) / self.scale[0], self.degree)  # (n_l, d+1)
        pb = legvander((np.asarray(m_axis, dtype=float) - self.centre[1]) / self.scale[1], self.degree)  # (n_m, d+1)
        u = np.einsum("mi,li->ml", np.einsum("mj,ij->mi", pb, self.coef_u), pa)
        v = np.einsum("mi,li->ml", np.einsum("mj,ij->mi", pb, self.coef_v), pa)
        return u, v

    def __call__(self, L: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) at scattered (L, M)."""
        pa = legvander((np.asarray(L, dtype=float) - self.centre[0]) / self.scale[0], self.degree)
        pb = legvander((np.asarray(M, dtype=float) - self.centre[1]) / self.scale[1], self.degree)
        return np.einsum("nj,ij,ni->n", pb, self.coef_u, pa), np.einsum("nj,ij,ni->n", pb, self.coef_v, pa)


def fit_pupil_map(L: np.ndarray, M: np.ndarray, u: np.ndarray, v: np.ndarray, degree: int = MAP_DEGREE) -> PupilMap:
    """Least-squares fit of (u, v) as Legendre polynomials of total degree ``degree`` in (L, M)."""
    L, M, u, v = (np.asarray(x, dtype=float) for x in (L, M, u, v))
    powers = _powers(degree)
    if L.size < len(powers):
        raise ValueError(f"{L.size} rays cannot fit a degree-{degree} pupil map ({len(powers)} terms)")
    centre = (float(0.5 * (L.max() + L.min())), float(0.5 * (M.max() + M.min())))
    scale = (float(np.ptp(L) / 2) or 1.0, float(np.ptp(M) / 2) or 1.0)
    pa = legvander((L - centre[0]) / scale[0], degree)
    pb = legvander((M - centre[1]) / scale[1], degree)
    basis = np.stack([pa[:, i] * pb[:, j] for i, j in powers], axis=1)
    target = np.column_stack([u, v])
    coef = solve_least_squares(basis, target)
    residual = float(np.sqrt(np.mean((np.einsum("ni,ik->nk", basis, coef) - target) ** 2)))
    cu = np.zeros((degree + 1, degree + 1))
    cv = np.zeros((degree + 1, degree + 1))
    for (i, j), a, b in zip(powers, coef[:, 0], coef[:, 1], strict=True):
        cu[i, j], cv[i, j] = a, b
    return PupilMap(centre, scale, cu, cv, degree, residual)


def fft_size(window_samples: int, extent: float, pitch_mm: float, wavelength_mm: float) -> tuple[int, float]:
    """FFT side N and direction-grid spacing ΔL = λ/(N h) for an output of ``window_samples`` at
    pitch h = ``pitch_mm``: the period N·h ≥ :data:`PERIOD_FACTOR` × window and ≥
    :data:`MIN_SAMPLES` samples span the pupil ``extent`` (in direction cosines)."""
    need = max(PERIOD_FACTOR * window_samples, MIN_SAMPLES * wavelength_mm / (max(extent, 1e-9) * pitch_mm))
    n = scipy.fft.next_fast_len(int(math.ceil(need)))
    if n > MAX_FFT:
        raise ValueError(f"a PSF would need a {n}² FFT (> {MAX_FFT}²): reduce the window or raise subpixel_um")
    return n, wavelength_mm / (n * pitch_mm)


def debye_fft(
    pupil: np.ndarray,
    spacing: float,
    wavelength_mm: float,
    n_fft: int,
    x0_mm: float,
    y0_mm: float,
    shape: tuple[int, int],
) -> np.ndarray:
    """Intensity (power per mm²) of the Debye integral of ``pupil`` on a grid of pitch
    h = λ/(n_fft ΔL), first sample at (x0, y0) relative to the reference point of W.

    pupil: (n_m, n_l) complex A·e^{ikW}, |A|² in power per unit dL dM, on a grid of spacing
    ``spacing`` (= ΔL = ΔM) centred on index (n − 1)/2 along each axis. shape: (rows, cols) of
    the output kept (≤ n_fft). The output is exact for the samples (no interpolation).
    """
    n_m, n_l = pupil.shape
    k = 2.0 * math.pi / wavelength_mm
    jl = np.arange(n_l) - (n_l - 1) / 2
    jm = np.arange(n_m) - (n_m - 1) / 2
    ramp = np.exp(1j * k * spacing * (jm[:, None] * y0_mm + jl[None, :] * x0_mm))
    # Place the centred pupil index j at FFT index j mod n (half-integer centres: shift by 1/2
    # sample with a ramp over the output, which only changes the field's phase).
    il = np.floor(jl).astype(int) % n_fft
    im = np.floor(jm).astype(int) % n_fft
    big = np.zeros((n_fft, n_fft), dtype=np.complex64)
    big[np.ix_(im, il)] = (pupil * ramp).astype(np.complex64)
    field = scipy.fft.ifft2(big, workers=1)[: shape[0], : shape[1]] * n_fft * n_fft
    # Half-sample offsets of the pupil index shift the output phase only: |.|² is unchanged,
    # except for the linear factor e^{2πi·frac·a/n}, a pure phase. Intensity:
    scale = spacing * spacing / wavelength_mm
    return (field.real**2 + field.imag**2) * scale * scale


def mft(
    pupil: np.ndarray,
    l_axis: np.ndarray,
    m_axis: np.ndarray,
    x_mm: np.ndarray,
    y_mm: np.ndarray,
    wavelength_mm: float,
    spacing: float,
) -> np.ndarray:
    """Intensity (power per mm²) of the Debye integral of ``pupil`` on the grid ``y_mm`` × ``x_mm``
    (relative to the reference point of W, mm), by a matrix Fourier transform.

    pupil: (n_m, n_l) complex A·e^{ikW}, |A|² in power per unit dL dM, at direction cosines
    ``l_axis`` (n_l,) and ``m_axis`` (n_m,). spacing: ΔL = ΔM.
    """
    k = 2.0 * math.pi / wavelength_mm
    ex = np.exp(1j * k * np.outer(l_axis, x_mm))  # (n_l, nx)
    ey = np.exp(1j * k * np.outer(y_mm, m_axis))  # (ny, n_m)
    field = (ey @ pupil @ ex) * (spacing * spacing / wavelength_mm)
    return field.real**2 + field.imag**2
