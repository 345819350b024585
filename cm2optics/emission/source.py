"""Point sources: a pinhole (or bead) of finite diameter with an angular emission profile.

The source emits towards the device (−z in the device frame), into the hemisphere around its
axis; θ is the angle from that axis. A profile gives the relative radiant intensity I(θ)/I(0);
:meth:`AngularProfile.intensity_sr` turns it into power per steradian for a source of unit
total power, so that a ray bundle of solid angle dΩ at θ carries ``intensity_sr(θ)·dΩ`` of it.

Profiles (:class:`ProfileKind`):

* ``isotropic``: I = 1 (a fluorescent bead);
* ``lambertian``: I = cos θ;
* ``cosine``: I = cosᵐ θ, m = ``parameter``;
* ``gaussian``: I = exp(−2 θ² / θ_e²), θ_e = ``parameter`` (deg), the half-angle at 1/e²;
* ``table``: I tabulated at ``angles_deg`` (linear in between, the last value held beyond).

The calibration pinhole of the paper (a 5-µm pinhole behind stacked diffusing films on a
green LED, Supplement §"Sparse PSF calibration") is not isotropic: "a large divergence angle
(> 60°)", and the point source's intensity under the central lenslet "drops as much as ≈ 85 %
near the edge" of the 8-mm field. :func:`calibration_pinhole` models it as a 5-µm disc with a
Gaussian profile of 1/e² half-angle 26°: with the ≈ cos³ θ fall of the lenslet's solid angle
and the filter's blue shift, the central lenslet then collects 85 % less from a source at the
edge of the field (4 mm off axis) than on axis (the tests check it); the profile falls to 5 %
at 32° (a 64° full divergence at that level, the paper's "> 60°").

The diameter acts in the image: the PSF is convolved with the source's geometric image, a
uniform disc of diameter |m|·d (m the lateral, chief-ray magnification at the source's depth).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from scipy.integrate import quad

__all__ = [
    "AngularProfile",
    "PointSource",
    "ProfileKind",
    "calibration_pinhole",
    "fluorescent_bead",
    "scan_source",
]


class ProfileKind(StrEnum):
    """Shape of a source's angular emission profile."""

    ISOTROPIC = "isotropic"
    LAMBERTIAN = "lambertian"
    COSINE = "cosine"
    GAUSSIAN = "gaussian"
    TABLE = "table"


@dataclass(frozen=True)
class AngularProfile:
    """Relative radiant intensity I(θ)/I(0) of a source (see the module docstring).

    kind: the profile's shape. parameter: cosine exponent m (cosine, 0–100) or the 1/e²
    half-angle θ_e in degrees (gaussian, 1–180); unused otherwise. angles_deg, relative: the
    table (kind ``table``): angles 0–90°, increasing, starting at 0; values ≥ 0, not all 0.
    """

    kind: ProfileKind = ProfileKind.ISOTROPIC
    parameter: float = 0.0
    angles_deg: tuple[float, ...] = ()
    relative: tuple[float, ...] = ()
    _norm: float = field(init=False, repr=False, compare=False, default=0.0)

    def __post_init__(self) -> None:
        kind = ProfileKind(self.kind)
        object.__setattr__(self, "kind", kind)
        if kind is ProfileKind.COSINE and not (math.isfinite(self.parameter) and 0 <= self.parameter <= 100):
            raise ValueError(f"parameter = {self.parameter!r}: a cosine exponent must lie within 0–100")
        if kind is ProfileKind.GAUSSIAN and not (math.isfinite(self.parameter) and 1 <= self.parameter <= 180):
            raise ValueError(f"parameter = {self.parameter!r}: a Gaussian 1/e² half-angle must lie within 1–180°")
        if kind is ProfileKind.TABLE:
            a = np.asarray(self.angles_deg, dtype=float)
            r = np.asarray(self.relative, dtype=float)
            if a.ndim != 1 or a.size < 2 or r.shape != a.shape:
                raise ValueError("angles_deg and relative must be two sequences of the same length ≥ 2")
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(r))):
                raise ValueError("angles_deg and relative must be finite (no NaN)")
            if a[0] != 0 or np.any(np.diff(a) <= 0) or a[-1] > 90:
                raise ValueError(f"angles_deg = {tuple(a)}: must start at 0 and increase strictly up to ≤ 90°")
            if np.any(r < 0) or not r.max() > 0:
                raise ValueError("relative must be ≥ 0 and not all zero")
        kinks = np.radians(self.angles_deg[1:-1]) if kind is ProfileKind.TABLE else None  # a table's corners
        norm, _ = quad(
            lambda t: float(self.relative_intensity(t)) * math.sin(t), 0.0, math.pi / 2, limit=200, points=kinks
        )
        object.__setattr__(self, "_norm", 2 * math.pi * norm)

    def relative_intensity(self, theta_rad: float | np.ndarray) -> np.ndarray:
        """I(θ)/I(0) at ``theta_rad`` (rad from the source's axis); 0 beyond 90°."""
        t = np.abs(np.asarray(theta_rad, dtype=float))
        if self.kind is ProfileKind.ISOTROPIC:
            out = np.ones_like(t)
        elif self.kind is ProfileKind.LAMBERTIAN:
            out = np.cos(t)
        elif self.kind is ProfileKind.COSINE:
            out = np.cos(t) ** self.parameter
        elif self.kind is ProfileKind.GAUSSIAN:
            out = np.exp(-2.0 * (t / math.radians(self.parameter)) ** 2)
        else:
            a = np.radians(np.asarray(self.angles_deg, dtype=float))
            out = np.interp(
                t,
                a,
                np.asarray(self.relative, dtype=float) / self.relative[0]
                if self.relative[0] > 0
                else np.asarray(self.relative),
            )
        return np.where(t <= math.pi / 2, np.clip(out, 0.0, None), 0.0)

    def intensity_sr(self, theta_rad: float | np.ndarray) -> np.ndarray:
        """Radiant intensity (fraction of the source's power per steradian) at ``theta_rad`` (rad)."""
        return self.relative_intensity(theta_rad) / self._norm

    @classmethod
    def parse(cls, text: str) -> AngularProfile:
        """The profile :meth:`describe` wrote (as a scan's ``source_profile`` records it):
        ``isotropic``, ``lambertian``, ``cos^M`` or ``gaussian, 1/e^2 half-angle A deg``. A table
        cannot be told by its description; ValueError for it and for any other text."""
        words = str(text).strip().lower()
        if words in (ProfileKind.ISOTROPIC, ProfileKind.LAMBERTIAN):
            return cls(ProfileKind(words))
        cosine = re.fullmatch(r"cos\^\s*([0-9.eE+-]+)", words)
        if cosine:
            return cls(ProfileKind.COSINE, float(cosine.group(1)))
        gaussian = re.fullmatch(r"gaussian,?\s*1/e\^?2 half-angle\s*([0-9.eE+-]+)\s*deg(rees)?", words)
        if gaussian:
            return cls(ProfileKind.GAUSSIAN, float(gaussian.group(1)))
        raise ValueError(
            f"source profile {text!r}: expected 'isotropic', 'lambertian', 'cos^M' or "
            "'gaussian, 1/e^2 half-angle A deg'"
        )

    def describe(self) -> str:
        if self.kind is ProfileKind.COSINE:
            return f"cos^{self.parameter:g}"
        if self.kind is ProfileKind.GAUSSIAN:
            return f"gaussian, 1/e^2 half-angle {self.parameter:g} deg"
        if self.kind is ProfileKind.TABLE:
            return f"table of {len(self.angles_deg)} angles"
        return self.kind.value


@dataclass(frozen=True)
class PointSource:
    """A small source: a uniform disc of ``diameter_um`` (µm, 0–200; 0 for an ideal point) in the
    object plane, emitting with ``profile``."""

    diameter_um: float = 5.0
    profile: AngularProfile = field(default_factory=AngularProfile)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.diameter_um) and 0 <= self.diameter_um <= 200):
            raise ValueError(f"diameter_um = {self.diameter_um!r}: must lie within 0–200 µm")
        if not isinstance(self.profile, AngularProfile):
            raise ValueError(f"profile = {self.profile!r}: must be an AngularProfile")

    def describe(self) -> str:
        return f"{self.diameter_um:g}-um disc, {self.profile.describe()} profile"


#: 1/e² half-angle of the calibration pinhole's Gaussian profile (deg): see the module docstring.
PINHOLE_HALF_ANGLE_DEG = 26.0


def calibration_pinhole(diameter_um: float = 5.0, half_angle_deg: float = PINHOLE_HALF_ANGLE_DEG) -> PointSource:
    """The paper's calibration source: a ``diameter_um`` pinhole (µm) behind a diffuser, with a
    Gaussian profile of 1/e² half-angle ``half_angle_deg`` (deg)."""
    return PointSource(diameter_um, AngularProfile(ProfileKind.GAUSSIAN, half_angle_deg))


def fluorescent_bead(diameter_um: float) -> PointSource:
    """A fluorescent bead of ``diameter_um`` (µm): isotropic emission."""
    return PointSource(diameter_um, AngularProfile(ProfileKind.ISOTROPIC))


def scan_source(profile: str, diameter_um: float, half_angle_deg: float = PINHOLE_HALF_ANGLE_DEG) -> PointSource:
    """The source of a scan by the name of its profile: ``gaussian`` (:func:`calibration_pinhole`
    with ``half_angle_deg``), ``isotropic`` (:func:`fluorescent_bead`) or ``lambertian``;
    ``diameter_um`` in µm."""
    if profile == ProfileKind.GAUSSIAN:
        return calibration_pinhole(diameter_um, half_angle_deg)
    if profile == ProfileKind.ISOTROPIC:
        return fluorescent_bead(diameter_um)
    if profile == ProfileKind.LAMBERTIAN:
        return PointSource(diameter_um, AngularProfile(ProfileKind.LAMBERTIAN))
    raise ValueError(f"--profile {profile!r}: choose gaussian, isotropic or lambertian")
