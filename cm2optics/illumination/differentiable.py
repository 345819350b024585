"""The illumination objective and its gradient with respect to the lens's Zernike terms, through Dr.Jit.

The trace is the tracer's own step (:class:`cm2optics.illumination.tracer._Kernel`: Mitsuba's
intersection, Fresnel, the coating's T(λ, θ), Snell, TIR, the smooth-normal fallback), run on
the mesh of the current coefficients, with four changes that make the objective differentiable:

* **attached geometry.** Mitsuba's hit points follow the (attached) rays. On the collimator the
  smooth normal is interpolated again in Dr.Jit, from the attached hit point's barycentric
  weights of its facet's corner normals; on the lens (a facet inside the cavity whose outward
  normal faces the LED — not the exit face above it) the Zernike sag ``S = Σ c_j Z_j`` adds its
  own change of height and slope (:func:`cm2optics.optics.freeform.zernike_with_gradient`):
  the hit point moves along the ray by ``δt = δS / (d_z − f_x d_x − f_y d_y)`` (implicit
  function, LED frame; ``f`` the lens height, its slopes from the shading normal), the base
  surface's normal is taken at the moved point (the curvature's share of the change) and the
  sag's slope is added to it, ``n ∝ (−f_x − δS_x, −f_y − δS_y, 1)``. Values stay exactly the
  mesh trace's: only the derivatives are attached (``x + (y − detach(y))``);
* **expected transmission.** No random reflect/refract choice: a ray refracts carrying the
  weight ``1 − R`` (Fresnel, or the coating's T) and reflects only under TIR. Deterministic and
  smooth, it drops the Fresnel-reflected light the tracer would still follow (a surrogate:
  the figures of merit of a design always come from :func:`cm2optics.illumination.tracer.trace`);
* **a bilinear splat** of each landed ray's weight into the uniformity bins (``bin_mm``, as
  :mod:`.metrics`), so the CV and the delivered fraction move smoothly with the hit points.

* **the lens rim's boundary term.** The terms without rotational symmetry (Noll 3, 6, 7) move
  the rim where the lens meets the cavity wall, by ``v(φ) = Σ_j δc_j Z_j(1, φ)`` (the piston
  holds it for 4 and 11), and the rays crossing the cavity's cylinder between its old and new
  height go to the wall instead of the lens: a jump that no attached derivative sees. Its
  derivative is estimated from the rays whose first segment crosses the cylinder within a band
  ``ε`` (``rim_band_mm``) about the rim: each is traced twice more, re-aimed 2 µm below the rim
  (onto the wall) and 2 µm above it (onto the lens), and splats ``± v(φ)/ε`` times its landed
  weight (zero-valued, attached): ``δH = Σ_band (H_wall − H_lens) v(φ)/ε``, the flux per unit
  height at the rim times the difference of the two fates. Unbiased up to the density's
  curvature over ``ε``; its noise falls as 1/√(rays in the band).

Not differentiated: other changes of visibility (a ray moving across a fixed edge — the
housing's aperture, the filter's edge — or between TIR and refraction). Against central finite
differences of this same objective (BENCHMARKS.md) on the same rays the comparison is limited by
the finite differences' own noise: the rays changing path between c ± h each move dD by
1/(2 h N).

Objective (maximised), the sweep's ranking (:mod:`.optimize`) on these smooth figures:
``J = D − 2 max(0, CV′ − max_cv)``, ``D`` the weight in the bins centred inside the field
circle over the power emitted, ``CV`` the standard deviation / mean of those bins and
``CV′ = √(CV² − CV_noise²)`` with the Monte Carlo noise (each bin's ``Σ (w b)²``, detached)
taken out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cm2optics.design import SystemDesign
from cm2optics.illumination.geometry import Medium, Role, build_scene, corner_normals
from cm2optics.illumination.scene import mitsuba_scene
from cm2optics.illumination.source import LEDSource
from cm2optics.illumination.tracer import DEFAULT_MAX_BOUNCES, _Kernel, emit_rays, filter_table
from cm2optics.optics.backend import is_jit, mitsuba
from cm2optics.optics.freeform import rim_piston_um, zernike, zernike_with_gradient

__all__ = ["CV_PENALTY", "RIM_BAND_MM", "SmoothFigures", "smooth_objective"]

#: Weight of the CV excess in the objective (the sweep's ranking).
CV_PENALTY = 2.0
#: −n_z of a facet's outward normal (LED frame) above which a hit inside the cavity is on the lens, not its wall.
_LENS_FACET_NZ = 0.3
#: Default width of the band of rays about the lens's rim that estimates its boundary term, mm.
RIM_BAND_MM = 0.04
#: How far above and below the rim (mm) a band ray is re-aimed to trace the lens's and the wall's side.
_RIM_NUDGE_MM = 0.002


@dataclass(frozen=True)
class SmoothFigures:
    """The smooth objective of one design and its gradient.

    objective: ``D − 2 max(0, CV′ − max_cv)``. delivered: D. cv, cv_noise, cv_corrected: the
    bins' CV, its Monte Carlo part and CV′. gradient, gradient_delivered, gradient_cv: dJ/dc_j,
    dD/dc_j and dCV′/dc_j for each term (1/µm). rays: rays traced.
    """

    objective: float
    delivered: float
    cv: float
    cv_noise: float
    cv_corrected: float
    gradient: np.ndarray
    gradient_delivered: np.ndarray
    gradient_cv: np.ndarray
    rays: int


class _LensAttachment:
    """Attaches the collimator's hit points and shading normals to the rays and to the
    lens's Zernike coefficients (see the module docstring)."""

    def __init__(self, scene: Any, terms: tuple[int, ...], coefficients: list[Any]):
        mi = mitsuba()
        import drjit as dr

        self.mi, self.dr = mi, dr
        profile_mesh = scene.collimator.mesh
        vertices = np.asarray(profile_mesh.vertices, dtype=float)
        faces = np.asarray(profile_mesh.faces, dtype=np.int64)
        normals = corner_normals(vertices, faces, scene.collimator.face_ids)  # the tracer's own (LED frame)
        self.corners = mi.Float(np.ascontiguousarray(vertices[faces], np.float32).ravel())  # (F, 3, 3)
        self.normals = mi.Float(np.ascontiguousarray(normals, np.float32).ravel())
        self.rotation = mi.Float(np.ascontiguousarray(scene.poses[:, :3, :3], np.float32).ravel())
        self.translation = mi.Float(np.ascontiguousarray(scene.poses[:, :3, 3], np.float32).ravel())
        design = scene.design
        from cm2optics.optics.collimator import collimator_profile

        profile = collimator_profile(design)
        self.radius = float(profile.cavity_radius_mm)
        self.entry_z, self.exit_z = float(profile.entry_z_mm), float(profile.exit_z_mm)
        # c − detach(c): zero, with the coefficient's derivative (µm); the piston follows the
        # rotationally symmetric terms so that the lens's rim stays put (rim_piston_um).
        delta = [c - dr.detach(c) for c in coefficients]
        self.terms = (1, *terms)
        self.delta = [rim_piston_um(terms, delta), *delta]

    def _matrix(self, unit: Any) -> list[list[Any]]:
        dr, mi = self.dr, self.mi
        return [[dr.gather(mi.Float, self.rotation, unit * 9 + 3 * i + k) for k in range(3)] for i in range(3)]

    def _vector(self, array: Any, base: Any) -> Any:
        dr, mi = self.dr, self.mi
        return mi.Vector3f(*(dr.gather(mi.Float, array, base + k) for k in range(3)))

    def __call__(self, si: Any, d: Any, unit: Any, on_collimator: Any) -> tuple[Any, Any]:
        """(hit point, shading normal) of ``si`` with attached derivatives on the collimator."""
        mi, dr = self.mi, self.dr
        rot = self._matrix(unit)
        t = self._vector(self.translation, unit * 3)

        def to_local(v: Any) -> Any:  # Rᵀ v
            return mi.Vector3f(*(rot[0][k] * v.x + rot[1][k] * v.y + rot[2][k] * v.z for k in range(3)))

        def to_device(v: Any) -> Any:  # R v
            return mi.Vector3f(*(rot[k][0] * v.x + rot[k][1] * v.y + rot[k][2] * v.z for k in range(3)))

        # The lens: inside the cavity, a facet whose outward normal faces the LED (−z). The exit
        # face above it (its outward normal +z, at z = exit_z) is not the lens.
        p_local = to_local(si.p - t)
        x, y, z = dr.detach(p_local.x), dr.detach(p_local.y), dr.detach(p_local.z)
        facet_nz = to_local(dr.detach(si.n)).z
        lens = (
            on_collimator
            & (facet_nz < -_LENS_FACET_NZ)
            & (x * x + y * y < self.radius * self.radius)
            & (z > self.entry_z)
            & (z < self.exit_z)
        )
        base = si.prim_index * 9
        v0, v1, v2 = (self._vector(self.corners, base + 3 * i) for i in range(3))
        n0, n1, n2 = (self._vector(self.normals, base + 3 * i) for i in range(3))

        def shading_normal(point: Any) -> Any:
            """The facet's smooth normal at ``point`` (LED frame; its projection on the facet)."""
            e1, e2, w = v1 - v0, v2 - v0, point - v0
            d00, d01, d11 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
            d20, d21 = dr.dot(w, e1), dr.dot(w, e2)
            det = d00 * d11 - d01 * d01
            b1 = (d11 * d20 - d01 * d21) / det
            b2 = (d00 * d21 - d01 * d20) / det
            return dr.normalize((1.0 - b1 - b2) * n0 + b1 * n1 + b2 * n2)

        sag, sag_x, sag_y = mi.Float(0.0), mi.Float(0.0), mi.Float(0.0)
        for j, delta in zip(self.terms, self.delta, strict=True):
            zj, zx, zy = zernike_with_gradient(j, x, y, self.radius, dr)
            sag, sag_x, sag_y = sag + 1e-3 * delta * zj, sag_x + 1e-3 * delta * zx, sag_y + 1e-3 * delta * zy
        slope = dr.detach(shading_normal(p_local))
        slope = slope / slope.z  # (−f_x, −f_y, 1)
        d_local = to_local(dr.detach(d))
        shift = d_local * (sag / (d_local.z + slope.x * d_local.x + slope.y * d_local.y))
        # On the lens the hit point moves along the ray onto the displaced surface, and the base
        # surface's normal is taken there (its curvature's share of the change) before the sag's slope.
        p_local = dr.select(lens, p_local + shift, p_local)
        normal = shading_normal(p_local)
        moved = normal / normal.z
        lens_normal = dr.normalize(mi.Vector3f(moved.x - sag_x, moved.y - sag_y, 1.0)) * dr.sign(normal.z)
        normal = dr.select(lens, lens_normal, normal)

        attached = to_device(normal)
        ns = dr.select(on_collimator, dr.detach(si.sh_frame.n) + (attached - dr.detach(attached)), si.sh_frame.n)
        p = dr.select(lens, si.p + to_device(shift), si.p)
        return mi.Point3f(p), mi.Normal3f(ns)


def _splat(dr: Any, mi: Any, hist: Any, noise: Any, x: Any, y: Any, w: Any, half: float, bin_mm: float, side: int):
    """Add weights ``w`` at (x, y) (mm) bilinearly to the ``side × side`` bins centred at
    ``−half + bin_mm (i + ½)``; ``noise`` gathers each bin's Σ (w b)², detached."""
    u = (x + half) / bin_mm - 0.5
    v = (y + half) / bin_mm - 0.5
    iu, iv = dr.floor(dr.detach(u)), dr.floor(dr.detach(v))
    fu, fv = u - iu, v - iv
    for du, dv, b in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        i, k = iu + du, iv + dv
        inside = (i >= 0) & (i < side) & (k >= 0) & (k < side)
        index = mi.UInt32(dr.maximum(k, 0) * side + dr.maximum(i, 0))
        dr.scatter_add(hist, w * b, index, inside)
        dr.scatter_add(noise, dr.detach(w * b) ** 2, index, inside)


@dataclass(frozen=True)
class _RimCrossings:
    """The LED rays whose first segment leaves the cavity's cylinder (radius ``a``) within half a
    band ``ε`` of the lens's rim: index into the batch, the crossing's azimuth φ (rad) and the
    two nudged directions (device frame) that cross at the rim ± ``_RIM_NUDGE_MM``, below onto
    the cavity wall and above onto the lens."""

    index: np.ndarray
    azimuth: np.ndarray
    below: np.ndarray
    above: np.ndarray


def _rim_crossings(scene: Any, batch: Any, band_mm: float) -> _RimCrossings:
    """The rays of ``batch`` crossing the rim's band (:class:`_RimCrossings`); the rim's height at
    azimuth φ is the lens edge's plus the sag ``S(a, φ)`` of the design's own terms."""
    from cm2optics.optics.collimator import collimator_profile
    from cm2optics.optics.freeform import lens_sag_mm

    collimator = scene.design.collimator
    profile = collimator_profile(scene.design)
    a, mouth = float(profile.cavity_radius_mm), float(profile.entry_z_mm)
    rot = scene.poses[batch.unit, :3, :3]
    o = np.einsum("nji,nj->ni", rot, batch.origin_mm - scene.poses[batch.unit, :3, 3])  # LED frame
    d = np.einsum("nji,nj->ni", rot, batch.direction)
    with np.errstate(divide="ignore", invalid="ignore"):
        at_mouth = o[:, :2] + d[:, :2] * ((mouth - o[:, 2]) / d[:, 2])[:, None]
        enters = (d[:, 2] > 0) & (np.einsum("ni,ni->n", at_mouth, at_mouth) < a * a)
        qa = np.einsum("ni,ni->n", d[:, :2], d[:, :2])
        qb = np.einsum("ni,ni->n", o[:, :2], d[:, :2])
        qc = np.einsum("ni,ni->n", o[:, :2], o[:, :2]) - a * a
        t = (-qb + np.sqrt(qb * qb - qa * qc)) / qa  # the outward crossing of r = a
    crossing = o + t[:, None] * d
    phi = np.arctan2(crossing[:, 1], crossing[:, 0])
    rim_z = profile.lens_edge_z_mm + lens_sag_mm(collimator.lens_freeform_um, a * np.cos(phi), a * np.sin(phi), a)
    index = np.flatnonzero(enters & np.isfinite(t) & (np.abs(crossing[:, 2] - rim_z) < band_mm / 2))
    phi, rim_z, o = phi[index], rim_z[index], o[index]

    def towards(dz: float) -> np.ndarray:
        target = np.column_stack([a * np.cos(phi), a * np.sin(phi), rim_z + dz]) - o
        target /= np.linalg.norm(target, axis=1, keepdims=True)
        return np.einsum("nij,nj->ni", rot[index], target)

    return _RimCrossings(index, phi, towards(-_RIM_NUDGE_MM), towards(_RIM_NUDGE_MM))


def smooth_objective(
    design: SystemDesign,
    collimator: Any,
    source: LEDSource,
    transmission: Any,
    terms: tuple[int, ...],
    rays: int,
    *,
    seed: int = 0,
    max_cv: float = 0.10,
    bin_mm: float = 0.5,
    max_bounces: int = DEFAULT_MAX_BOUNCES,
    rim_band_mm: float = RIM_BAND_MM,
) -> SmoothFigures:
    """Trace ``rays`` rays through ``design`` with ``collimator`` (its mesh built with the design's
    own lens terms) and return the smooth objective and its gradient with respect to the Noll
    ``terms`` (not 1) of ``design.collimator.lens_freeform_um`` (µm), the piston ``c_1`` following
    them (:func:`~cm2optics.optics.freeform.rim_piston_um`: the rotationally symmetric terms keep
    the lens's rim in place). The others move the rim, and rays switch between lens and cavity
    wall there: the boundary term of the module docstring, from the rays within ``rim_band_mm``
    (mm; 0: left out) of the rim. transmission: the excitation filter's T(λ, θ) (None without a
    filter). The same seed gives the same rays."""
    if 1 in terms:
        raise ValueError("the piston (Noll 1) follows the other terms: leave it out of terms")
    if not is_jit():
        raise RuntimeError("gradients need a Dr.Jit JIT variant (llvm_ad_rgb or cuda_ad_rgb), not the scalar fallback")
    mi = mitsuba()
    import drjit as dr

    scene = build_scene(design, collimator)
    msc = mitsuba_scene(scene)
    batch = emit_rays(scene, source, rays, seed)
    kernel = _Kernel(msc, filter_table(scene, source, transmission), max_bounces, seed)
    current = list(design.collimator.lens_freeform_um) + [0.0] * max(terms)
    coefficients = [mi.Float(current[j - 1]) for j in terms]
    for c in coefficients:
        dr.enable_grad(c)
    attach = _LensAttachment(scene, terms, coefficients)

    radius = scene.field_radius_mm
    half_u = bin_mm * math.ceil(radius / bin_mm)
    half = half_u + bin_mm  # one bin of margin: the splat reaches the circle's edge bins from outside
    side = int(round(2 * half / bin_mm))
    centres = -half + bin_mm * (np.arange(side) + 0.5)
    inside_np = (centres[None, :] ** 2 + centres[:, None] ** 2 <= radius**2).ravel()
    inside = mi.Float(inside_np.astype(np.float32))
    hist = dr.zeros(mi.Float, side * side)
    noise = dr.zeros(mi.Float, side * side)
    n_coll, n_filt = scene.refractive_indices(batch.wavelength_nm)

    def f32(values: np.ndarray) -> Any:
        return mi.Float(np.ascontiguousarray(values, dtype=np.float32))

    def trace(index: np.ndarray, direction: np.ndarray, weight: Any) -> None:
        """Trace the batch's rays ``index`` along ``direction`` (device frame) from their origins,
        starting with ``weight``, and splat what lands into ``hist``."""
        o = mi.Point3f(*(f32(batch.origin_mm[index, k]) for k in range(3)))
        d = mi.Vector3f(*(f32(direction[:, k]) for k in range(3)))
        wl, nc, nf = f32(batch.wavelength_nm[index]), f32(n_coll[index]), f32(n_filt[index])
        unit = mi.UInt32(batch.unit[index].astype(np.uint32))
        for _ in range(max_bounces):
            active = dr.full(mi.Bool, True, dr.width(unit))
            si = msc.scene.ray_intersect(mi.Ray3f(o, d), kernel.flags, False, active)
            active = si.is_valid()
            code = kernel.code(si, active)
            on_collimator = (
                active & ((code & 15) == int(Role.DIELECTRIC)) & (((code >> 4) & 15) == int(Medium.COLLIMATOR))
            )
            p, ns = attach(si, d, unit, on_collimator)
            si.p = p
            hit = kernel.surface(si, d, wl, nc, nf, active, ns)
            role = hit["role"]
            refracts = ((role == int(Role.DIELECTRIC)) | (role == int(Role.COATED))) & ~hit["tir"]
            weight = weight * dr.select(refracts, 1.0 - hit["reflectance"], 1.0)
            new_d, _ = kernel.scatter(d, hit, hit["tir"])
            new_d = mi.Vector3f(new_d)
            landed = active & (role == int(Role.SAMPLE))
            _splat(dr, mi, hist, noise, p.x, p.y, dr.select(landed, weight, 0.0), half, bin_mm, side)
            going = active & ~landed & (role != int(Role.ABSORBER))
            ray = si.spawn_ray(new_d)
            keep = dr.compress(going)
            if dr.width(keep) == 0:
                break
            o = dr.gather(mi.Point3f, ray.o, keep)
            d = dr.gather(mi.Vector3f, new_d, keep)
            weight = dr.gather(mi.Float, weight, keep)
            wl, nc, nf = (dr.gather(mi.Float, a, keep) for a in (wl, nc, nf))
            unit = dr.gather(mi.UInt32, unit, keep)
            dr.eval(o, d, weight, wl, nc, nf, unit, hist, noise)

    everything = np.arange(len(batch.unit))
    trace(everything, batch.direction, dr.ones(mi.Float, len(everything)))
    if rim_band_mm > 0:
        rim = _rim_crossings(scene, batch, rim_band_mm)
        if len(rim.index):
            # The rim rises by v(φ) = Σ_j δc_j Z_j(1, φ) (zero-valued, attached): the rays
            # crossing between its old and new height go to the wall instead of the lens.
            lift = mi.Float(0.0)
            for j, delta in zip(attach.terms, attach.delta, strict=True):
                lift = lift + delta * f32(1e-3 * zernike(j, np.ones_like(rim.azimuth), rim.azimuth))
            trace(rim.index, rim.below, lift / rim_band_mm)
            trace(rim.index, rim.above, -lift / rim_band_mm)

    emitted = float(len(batch.unit)) if not batch.rays_per_unit else float(batch.rays_per_unit * scene.units)
    n_inside = float(inside_np.sum())
    delivered = dr.sum(hist * inside) / emitted
    mean = dr.sum(hist * inside) / n_inside
    cv = dr.sqrt(dr.sum(dr.square(hist - mean) * inside) / n_inside) / mean
    cv_noise = dr.sqrt(dr.sum(noise * inside) / n_inside) / dr.detach(mean)
    cv_corrected = dr.sqrt(dr.maximum(dr.square(cv) - dr.square(cv_noise), 1e-8))
    penalised = float(cv_corrected[0]) > max_cv
    objective = delivered - CV_PENALTY * dr.maximum(cv_corrected - max_cv, 0.0)
    gradients = []
    for figure, flags in ((delivered, dr.ADFlag.ClearVertices), (cv_corrected, dr.ADFlag.Default)):
        # The first pass keeps the graph's edges for the second and clears the gradients it left.
        dr.backward(figure, flags=flags)
        gradients.append(np.array([float(dr.grad(c)[0]) for c in coefficients]))
        for c in coefficients:
            dr.clear_grad(c)
    grad_delivered, grad_cv = gradients
    return SmoothFigures(
        objective=float(objective[0]),
        delivered=float(delivered[0]),
        cv=float(cv[0]),
        cv_noise=float(cv_noise[0]),
        cv_corrected=float(cv_corrected[0]),
        gradient=grad_delivered - CV_PENALTY * penalised * grad_cv,
        gradient_delivered=grad_delivered,
        gradient_cv=grad_cv,
        rays=len(batch.unit),
    )
