"""The light tracer: LED rays through collimator, filter and housing onto the sample plane.

All rays advance together, one surface per step, in a Dr.Jit symbolic loop
(``dr.while_loop``): the whole path — intersection (Mitsuba), Fresnel, Snell, TIR, the filter's
T(λ, θ), absorption — compiles into one kernel that runs on every CPU core (LLVM) or on the
GPU (CUDA). No Python loop over rays; on the scalar fallback variant the very same body runs
one ray at a time.

At each surface (``n`` its normal, θᵢ the angle of incidence, indices n₁ → n₂ from the side
the ray comes from, η = n₁/n₂):

* dielectric (collimator): unpolarised Fresnel reflectance
  ``R = (r_s² + r_p²)/2``, ``r_s = (n₁cosθᵢ − n₂cosθₜ)/(n₁cosθᵢ + n₂cosθₜ)``,
  ``r_p = (n₂cosθᵢ − n₁cosθₜ)/(n₂cosθᵢ + n₁cosθₜ)``, ``R = 1`` when ``η sinθᵢ ≥ 1`` (TIR);
* coated filter face: ``R = 1 − T(λ, θ_air)``, θ_air the angle in air;
* bare filter face: ``R = 0`` (the filter's T already holds its losses), TIR still applies.

The ray is then reflected with probability R and refracted otherwise (``t = η d + (η cosθᵢ −
cosθₜ) n``) — an unbiased choice that keeps every ray's power whole, so each ray ends in
exactly one ledger entry and the energy ledger closes by construction. n(λ) of the
collimator's and the filter's materials is evaluated per ray at its wavelength (Mitsuba itself
has no dispersion).

Normals: smooth (interpolated) normals shade the collimator; where a smooth normal would send
the refracted or reflected ray to the wrong side of the actual facet, the facet's own normal is
used instead.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

from cm2optics.illumination.excitation import Transmission, TransmissionTable, tabulate_transmission
from cm2optics.illumination.geometry import IlluminationScene, Medium, Role
from cm2optics.illumination.scene import MitsubaScene, mitsuba_scene
from cm2optics.illumination.source import LEDSource, sample_led_rays
from cm2optics.optics.backend import is_jit, mitsuba, variant
from cm2optics.optics.interfaces import fresnel_reflectance, refract, snell_cos_t
from cm2optics.optics.interfaces import reflect as mirror

__all__ = [
    "DEFAULT_MAX_BOUNCES",
    "TEA_ROUNDS",
    "EmittedBatch",
    "RayRecord",
    "Status",
    "emit_rays",
    "filter_table",
    "random_stream",
    "trace",
    "trace_rays",
]

#: Surfaces a ray may meet before it is counted as truncated.
DEFAULT_MAX_BOUNCES = 64
#: Wavefront steps (one kernel launch each, survivors compacted) before the stragglers are
#: finished in one symbolic loop.
WAVEFRONT_STEPS = 12
#: Rounds of the TEA hash that draws the reflect/refract decisions.
TEA_ROUNDS = 8


def random_stream(seed: int) -> int:
    """Second TEA key of a trace: the decision of ray ``i`` at its ``k``-th surface is
    ``sample_tea_float32(i, random_stream(seed) + k)`` — stateless, so the scalar fallback and
    the NumPy reference tracer draw exactly the same numbers."""
    return (int(seed) * 65536) % 2**32


class Status(IntEnum):
    """How a ray ended. Absorbed rays carry ``ABSORBED + Absorber group``."""

    ACTIVE = 0
    SAMPLE = 1  # landed on the sample plane (inside or outside the field)
    ESCAPED = 2  # left the scene
    TRUNCATED = 3  # still bouncing after max_bounces surfaces
    ABSORBED = 10


@dataclass(frozen=True, eq=False)
class EmittedBatch:
    """Rays of every unit in the device frame, ready to trace (arrays of length N).

    unit: LED unit of each ray. origin_mm, direction: (N, 3). wavelength_nm: (N,), nm.
    power_mw: power carried by each ray, mW (the same for all).
    rays_per_unit: rays of a unit at the LED's nominal flux (0: N / units, every unit alike).
    """

    unit: np.ndarray
    origin_mm: np.ndarray
    direction: np.ndarray
    wavelength_nm: np.ndarray
    power_mw: float
    rays_per_unit: int = 0


@dataclass(frozen=True, eq=False)
class RayRecord:
    """The fate of every traced ray (NumPy arrays of length ``rays``).

    unit: LED unit that emitted the ray.
    status: :class:`Status` code (``ABSORBED + group`` for absorbed rays).
    hit_mm: (N, 2) x, y where the ray landed on the sample plane (device frame), mm; NaN otherwise.
    passed: the ray crossed its unit's portal outwards (it left the unit through the filter).
    exit_direction: (N, 3) direction in which it left the unit (after the portal, or out of the
        filter's back face into the air); NaN where it did not.
    wavelength_nm: the ray's wavelength, nm.
    bounces: surfaces met.
    power_mw: power of each ray, mW.
    units: number of LED units; rays_per_unit: rays a unit emits at the LED's nominal flux.
    seconds: wall time of the trace (sampling, tracing, copying back), s.
    variant: the Mitsuba variant that traced (``"numpy-reference"`` for the reference tracer).
    """

    unit: np.ndarray
    status: np.ndarray
    hit_mm: np.ndarray
    passed: np.ndarray
    exit_direction: np.ndarray
    wavelength_nm: np.ndarray
    bounces: np.ndarray
    power_mw: float
    units: int
    rays_per_unit: int
    seconds: float = 0.0
    variant: str = ""
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def rays(self) -> int:
        return int(self.status.size)


def _rotate(matrix: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``vectors @ matrix[:3, :3].T`` without BLAS (a (N, 3) × (3, 3) product is faster
    element-wise than through a threaded GEMM)."""
    r = matrix[:3, :3]
    return vectors[:, 0:1] * r[:, 0] + vectors[:, 1:2] * r[:, 1] + vectors[:, 2:3] * r[:, 2]


def emit_rays(scene: IlluminationScene, source: LEDSource, rays: int, seed: int) -> EmittedBatch:
    """``rays`` LED rays split evenly over the units (``rays // units`` each, at least 1),
    sampled with ``numpy.random.default_rng(seed)`` and placed in the device frame. A unit of
    relative flux f (``scene.led_flux``) emits ``round(f · rays // units)`` rays of the same power."""
    units = scene.units
    per_unit = max(int(rays) // units, 1)
    rng = np.random.default_rng(seed)
    origins, directions, wavelengths, unit_ids = [], [], [], []
    for unit, (matrix, flux) in enumerate(zip(scene.poses, scene.unit_flux, strict=True)):
        count = int(round(flux * per_unit))
        if count == 0:
            continue
        emitted = sample_led_rays(source, count, rng)
        origins.append(_rotate(matrix, emitted.origin_mm) + matrix[:3, 3])
        directions.append(_rotate(matrix, emitted.direction))
        wavelengths.append(emitted.wavelength_nm)
        unit_ids.append(np.full(count, unit, dtype=np.int32))
    return EmittedBatch(
        unit=np.concatenate(unit_ids),
        origin_mm=np.concatenate(origins),
        direction=np.concatenate(directions),
        wavelength_nm=np.concatenate(wavelengths),
        power_mw=source.radiant_flux_mw / per_unit,
        rays_per_unit=per_unit,
    )


def filter_table(scene: IlluminationScene, source: LEDSource, transmission: Transmission | None) -> TransmissionTable:
    """The filter's T tabulated over the LED's spectrum (a dummy when there is no filter)."""
    if not scene.has_filter:
        return TransmissionTable(0.0, 1.0, math.pi / 2, np.ones((2, 2)))
    if transmission is None:
        raise ValueError("the scene has an excitation filter: pass its transmission(wavelength_nm, aoi_rad)")
    lo, hi = source.spectrum.wavelength_nm[0], source.spectrum.wavelength_nm[-1]
    return tabulate_transmission(transmission, (float(lo), float(hi)))


# ----------------------------------------------------------------------------- the kernel


def _not(mask: Any) -> Any:
    """Logical not of a mask: a Dr.Jit array or a Python bool (scalar variant)."""
    return (not mask) if isinstance(mask, bool) else ~mask


class _Kernel:
    """The per-surface step, written once for Dr.Jit arrays (JIT) and Python scalars."""

    def __init__(self, msc: MitsubaScene, table: TransmissionTable, max_bounces: int, seed: int):
        self.mi = mitsuba()
        import drjit as dr

        self.dr = dr
        self.msc = msc
        self.jit = is_jit()
        self.max_bounces = int(max_bounces)
        self.stream = random_stream(seed)
        self.table_np = table
        # Position, geometric normal and the (smooth) shading normal: nothing else is needed.
        self.flags = self.mi.RayFlags.Minimal | self.mi.RayFlags.ShadingFrame
        n_aoi, n_wl = table.values.shape
        self.n_aoi, self.n_wl = n_aoi, n_wl
        if self.jit:
            self.table = self.mi.Float(np.ascontiguousarray(table.values, dtype=np.float32).ravel())

    def code(self, si: Any, active: Any) -> Any:
        mi, dr = self.mi, self.dr
        if self.jit:
            shape_id = dr.reinterpret_array(mi.UInt32, si.shape)
            return dr.gather(mi.UInt32, self.msc.codes_by_id, shape_id, active)
        return self.msc.codes_by_id[si.shape.id()] if active else 0

    def coating(self, wl: Any, aoi: Any, active: Any) -> Any:
        """Bilinear lookup of T(λ, θ), the same as :meth:`TransmissionTable.__call__`."""
        if not self.jit:
            return float(self.table_np(wl, aoi))
        mi, dr = self.mi, self.dr
        t = self.table_np
        fw = dr.clip((wl - t.wavelength_start_nm) / t.wavelength_step_nm, 0.0, self.n_wl - 1.0)
        fa = dr.clip(aoi / t.aoi_step_rad, 0.0, self.n_aoi - 1.0)
        iw = dr.minimum(mi.UInt32(dr.floor(fw)), self.n_wl - 2)
        ia = dr.minimum(mi.UInt32(dr.floor(fa)), self.n_aoi - 2)
        tw, ta = fw - mi.Float(iw), fa - mi.Float(ia)
        base = ia * self.n_wl + iw

        def at(offset: Any) -> Any:
            return dr.gather(mi.Float, self.table, base + offset, active)

        return dr.lerp(dr.lerp(at(0), at(1), tw), dr.lerp(at(self.n_wl), at(self.n_wl + 1), tw), ta)

    @staticmethod
    def _directions(dr: Any, d: Any, facing: Any, eta: Any, reflect: Any) -> Any:
        """Reflected (where ``reflect``) or refracted direction of ``d`` about the unit
        normal ``facing`` (which points against ``d``)."""
        cos_i = dr.clip(-dr.dot(d, facing), 0.0, 1.0)
        cos_t, _ = snell_cos_t(dr, cos_i, eta)
        return dr.select(reflect, mirror(d, facing, cos_i), refract(d, facing, eta, cos_i, cos_t))

    def surface(self, si: Any, d: Any, wl: Any, n_coll: Any, n_filt: Any, active: Any, ns: Any) -> dict[str, Any]:
        """What the surface hit at ``si`` does to a ray of direction ``d`` (shading normal ``ns``):
        role, medium, absorber group, whether the ray enters the solid, the geometric and shading
        normals facing the ray, η = n₁/n₂, the reflectance R (Fresnel, coating, 0 on bare
        glass, 1 under TIR) and the TIR flag."""
        dr = self.dr
        code = self.code(si, active)
        role = code & 15
        medium = (code >> 4) & 15
        group = code >> 8

        ng = si.n
        ns = dr.select(dr.dot(ns, ng) < 0.0, -ns, ns)
        entering = dr.dot(d, ng) < 0.0
        n_solid = dr.select(medium == int(Medium.FILTER), n_filt, n_coll)
        n1 = dr.select(entering, 1.0, n_solid)
        n2 = dr.select(entering, n_solid, 1.0)
        eta = n1 / n2
        face_g = dr.select(entering, ng, -ng)
        face_s = dr.select(entering, ns, -ns)
        face_s = dr.select(dr.dot(d, face_s) < 0.0, face_s, face_g)

        cos_i = dr.clip(-dr.dot(d, face_s), 0.0, 1.0)
        sin_i = dr.safe_sqrt(1.0 - cos_i * cos_i)
        cos_t, tir = snell_cos_t(dr, cos_i, eta)
        reflectance = fresnel_reflectance(cos_i, cos_t, n1, n2)
        coated = role == int(Role.COATED)
        sin_air = dr.minimum(dr.select(entering, sin_i, n_solid * sin_i), 1.0)
        aoi_air = dr.asin(sin_air)
        reflectance = dr.select(coated, 1.0 - self.coating(wl, aoi_air, active & coated), reflectance)
        reflectance = dr.select(role == int(Role.GLASS), 0.0, reflectance)
        reflectance = dr.select(tir, 1.0, reflectance)
        return {
            "role": role,
            "medium": medium,
            "group": group,
            "entering": entering,
            "face_g": face_g,
            "face_s": face_s,
            "eta": eta,
            "reflectance": reflectance,
            "tir": tir,
        }

    def scatter(self, d: Any, hit: dict[str, Any], reflect: Any) -> tuple[Any, Any]:
        """(new unit direction, reflected?) of ``d`` at the surface ``hit`` (:meth:`surface`),
        reflected where ``reflect``; a smooth normal that would send the ray to the wrong side of
        the facet is replaced by the facet's own, and a portal lets the ray through."""
        dr = self.dr
        face_s, face_g, eta = hit["face_s"], hit["face_g"], hit["eta"]
        new_d = self._directions(dr, d, face_s, eta, reflect)
        # A smooth normal must not send the ray to the wrong side of the actual facet.
        side = dr.dot(new_d, face_g)
        wrong = dr.select(reflect, side <= 0.0, side >= 0.0)
        cos_g = dr.dot(d, face_g)
        reflect_g = reflect | snell_cos_t(dr, cos_g, eta)[1]
        new_d = dr.select(wrong, self._directions(dr, d, face_g, eta, reflect_g), new_d)
        reflect = dr.select(wrong, reflect_g, reflect)
        new_d = dr.normalize(dr.select(hit["role"] == int(Role.PORTAL), d, new_d))
        return new_d, reflect

    def step(
        self, o: Any, d: Any, ray_id: Any, depth: Any, wl: Any, n_coll: Any, n_filt: Any, passed: Any, active: Any
    ) -> tuple:
        """Carry every ray in ``active`` to its next surface and act there.

        Returns (o, d, status, hit_x, hit_y, crossing): the new origin and direction,
        the ray's status (``ACTIVE`` while it goes on), where it landed on the sample plane,
        and whether it crossed its portal outwards for the first time at this step.
        """
        mi, dr = self.mi, self.dr
        status = dr.zeros(mi.UInt32, dr.width(active)) if self.jit else int(Status.ACTIVE)
        si = self.msc.scene.ray_intersect(mi.Ray3f(o, d), self.flags, False, active)
        valid = si.is_valid()
        status = dr.select(active & _not(valid), int(Status.ESCAPED), status)
        active = active & valid
        hit = self.surface(si, d, wl, n_coll, n_filt, active, si.sh_frame.n)
        role, entering = hit["role"], hit["entering"]
        reflect = mi.sample_tea_float32(ray_id, self.stream + depth, TEA_ROUNDS) < hit["reflectance"]
        new_d, reflect = self.scatter(d, hit, reflect)
        portal = role == int(Role.PORTAL)

        leaving_filter = (role == int(Role.GLASS)) & _not(entering) & _not(reflect)
        crossing = active & ((portal & (dr.dot(d, si.n) > 0.0)) | leaving_filter) & _not(passed)
        absorbed = active & (role == int(Role.ABSORBER))
        status = dr.select(absorbed, int(Status.ABSORBED) + hit["group"], status)
        landed = active & (role == int(Role.SAMPLE))
        status = dr.select(landed, int(Status.SAMPLE), status)
        hit_x = dr.select(landed, si.p.x, math.nan)
        hit_y = dr.select(landed, si.p.y, math.nan)
        active = active & _not(absorbed) & _not(landed)
        ray = si.spawn_ray(new_d)
        o = dr.select(active, ray.o, o)
        d = dr.select(active, new_d, d)
        truncated = active & (depth + 1 >= self.max_bounces)
        status = dr.select(truncated, int(Status.TRUNCATED), status)
        return o, d, status, hit_x, hit_y, crossing

    def run(self, batch: EmittedBatch, n_coll: np.ndarray, n_filt: np.ndarray, offset: int) -> dict[str, np.ndarray]:
        """Trace ``batch`` (its rays numbered from ``offset`` for the random streams)."""
        if self.jit:
            return self._run_wavefronts(batch, n_coll, n_filt, offset)
        return self._run_scalar(batch, n_coll, n_filt, offset)

    def _run_wavefronts(
        self, batch: EmittedBatch, n_coll: np.ndarray, n_filt: np.ndarray, offset: int
    ) -> dict[str, np.ndarray]:
        """Wavefronts: every step traces all live rays in one kernel; finished rays are
        written out and the survivors compacted, so late steps cost what their few rays cost."""
        mi, dr = self.mi, self.dr
        count = len(batch.unit)

        def f32(values: np.ndarray) -> Any:
            return mi.Float(np.ascontiguousarray(values, dtype=np.float32))

        o = mi.Point3f(*(f32(batch.origin_mm[:, k]) for k in range(3)))
        d = mi.Vector3f(*(f32(batch.direction[:, k]) for k in range(3)))
        wl, nc, nf = f32(batch.wavelength_nm), f32(n_coll), f32(n_filt)
        index = dr.arange(mi.UInt32, count)
        ray_id = index + offset
        passed = dr.full(mi.Bool, False, count)
        out_status = dr.zeros(mi.UInt32, count)
        out_hx = dr.full(mi.Float, math.nan, count)
        out_hy = dr.full(mi.Float, math.nan, count)
        out_passed = dr.full(mi.Bool, False, count)
        out_exit = [dr.full(mi.Float, math.nan, count) for _ in range(3)]
        out_bounces = dr.zeros(mi.UInt32, count)
        depth = 0
        while dr.width(index) > 0:
            if depth >= WAVEFRONT_STEPS:
                # The stragglers: finish them in one symbolic loop (one kernel) rather than in
                # dozens of launches that each cost more in overhead than their few rays.
                status, hx, hy, bounces, crossed, ex, ey, ez = self._tail(o, d, ray_id, depth, wl, nc, nf, passed)
                dr.scatter(out_status, status, index)
                dr.scatter(out_hx, hx, index)
                dr.scatter(out_hy, hy, index)
                dr.scatter(out_bounces, bounces, index)
                dr.scatter(out_passed, True, index, crossed)
                for k, component in enumerate((ex, ey, ez)):
                    dr.scatter(out_exit[k], component, index, crossed)
                dr.eval(out_status, out_hx, out_hy, out_bounces, out_passed, out_exit)
                break
            live = dr.full(mi.Bool, True, dr.width(index))
            o2, d2, status, hx, hy, crossing = self.step(
                o, d, ray_id, dr.opaque(mi.UInt32, depth), wl, nc, nf, passed, live
            )
            done = status != int(Status.ACTIVE)
            dr.scatter(out_passed, True, index, crossing)
            for k, component in enumerate((d2.x, d2.y, d2.z)):
                dr.scatter(out_exit[k], component, index, crossing)
            dr.scatter(out_status, status, index, done)
            dr.scatter(out_hx, hx, index, done)
            dr.scatter(out_hy, hy, index, done)
            dr.scatter(out_bounces, dr.opaque(mi.UInt32, depth + 1), index, done)
            passed = passed | crossing
            dr.eval(o2, d2, passed, done, out_status, out_hx, out_hy, out_passed, out_exit, out_bounces)
            keep = dr.compress(~done)
            depth += 1
            if dr.width(keep) == 0:
                break
            index, ray_id = dr.gather(mi.UInt32, index, keep), dr.gather(mi.UInt32, ray_id, keep)
            o = dr.gather(mi.Point3f, o2, keep)
            d = dr.gather(mi.Vector3f, d2, keep)
            wl, nc, nf = (dr.gather(mi.Float, a, keep) for a in (wl, nc, nf))
            passed = dr.gather(mi.Bool, passed, keep)
            dr.eval(index, ray_id, o, d, wl, nc, nf, passed)
        return {
            "bounces": out_bounces.numpy(),
            "status": out_status.numpy(),
            "hit": np.column_stack([out_hx.numpy(), out_hy.numpy()]),
            "passed": out_passed.numpy(),
            "exit": np.column_stack([c.numpy() for c in out_exit]),
        }

    def _tail(self, o: Any, d: Any, ray_id: Any, depth0: int, wl: Any, nc: Any, nf: Any, passed: Any) -> tuple:
        """Trace rays to their end in a symbolic ``dr.while_loop``; returns status, hit x, y,
        surfaces met, whether they passed (newly) and the direction when they did."""
        mi, dr = self.mi, self.dr
        n = dr.width(ray_id)
        nan = dr.full(mi.Float, math.nan, n)
        state = (
            o,
            d,
            dr.opaque(mi.UInt32, depth0, n),
            passed,
            dr.full(mi.Bool, False, n),
            dr.full(mi.Bool, True, n),
            dr.zeros(mi.UInt32, n),
            mi.Float(nan),
            mi.Float(nan),
            mi.Float(nan),
            mi.Float(nan),
            mi.Float(nan),
        )

        def body(o, d, depth, passed, crossed, active, status, hx, hy, ex, ey, ez):
            o2, d2, st, hx2, hy2, crossing = self.step(o, d, ray_id, depth, wl, nc, nf, passed, active)
            ex = dr.select(crossing, d2.x, ex)
            ey = dr.select(crossing, d2.y, ey)
            ez = dr.select(crossing, d2.z, ez)
            passed = passed | crossing
            crossed = crossed | crossing
            done = active & (st != int(Status.ACTIVE))
            status = dr.select(done, st, status)
            hx = dr.select(done, hx2, hx)
            hy = dr.select(done, hy2, hy)
            depth = dr.select(active, depth + 1, depth)
            return o2, d2, depth, passed, crossed, active & ~done, status, hx, hy, ex, ey, ez

        final = dr.while_loop(state, lambda *s: s[5], body, label="cm2_illumination_tail")
        _, _, depth, _, crossed, _, status, hx, hy, ex, ey, ez = final
        return status, hx, hy, depth, crossed, ex, ey, ez

    def _run_scalar(
        self, batch: EmittedBatch, n_coll: np.ndarray, n_filt: np.ndarray, offset: int
    ) -> dict[str, np.ndarray]:
        """The scalar fallback: the same step, one ray at a time."""
        mi = self.mi
        count = len(batch.unit)
        out = {
            "bounces": np.zeros(count, np.uint32),
            "status": np.zeros(count, np.uint32),
            "hit": np.full((count, 2), np.nan),
            "passed": np.zeros(count, bool),
            "exit": np.full((count, 3), np.nan),
        }
        for i in range(count):
            o, d = mi.Point3f(*batch.origin_mm[i]), mi.Vector3f(*batch.direction[i])
            wl, nc, nf = float(batch.wavelength_nm[i]), float(n_coll[i]), float(n_filt[i])
            passed, depth, status = False, 0, int(Status.ACTIVE)
            while status == int(Status.ACTIVE):
                o, d, status, hx, hy, crossing = self.step(o, d, offset + i, depth, wl, nc, nf, passed, True)
                if crossing:
                    passed = True
                    out["exit"][i] = d.x, d.y, d.z
                depth += 1
            out["bounces"][i], out["status"][i], out["passed"][i] = depth, status, passed
            out["hit"][i] = hx, hy
        return out


def trace_rays(
    scene: IlluminationScene,
    batch: EmittedBatch,
    table: TransmissionTable,
    *,
    seed: int = 0,
    max_bounces: int = DEFAULT_MAX_BOUNCES,
    batch_rays: int = 1 << 22,
    msc: MitsubaScene | None = None,
) -> RayRecord:
    """Trace the given rays (device frame) through ``scene``.

    table: the excitation filter's T(λ, θ) on a grid (:func:`filter_table`). seed: selects
    the random stream of the reflect/refract decisions. max_bounces: surfaces per ray before it
    is counted as truncated. batch_rays: rays per wavefront batch (bounds memory).
    msc: the scene already loaded with :func:`mitsuba_scene` (to trace one scene repeatedly).
    """
    if max_bounces < 1:
        raise ValueError(f"max_bounces = {max_bounces}: must be ≥ 1")
    start = time.perf_counter()
    n_coll, n_filt = scene.refractive_indices(batch.wavelength_nm)
    msc = msc if msc is not None else mitsuba_scene(scene)
    kernel = _Kernel(msc, table, max_bounces, seed)
    parts = []
    count = len(batch.unit)
    for lo in range(0, count, batch_rays):
        hi = min(lo + batch_rays, count)
        sub = EmittedBatch(
            batch.unit[lo:hi],
            batch.origin_mm[lo:hi],
            batch.direction[lo:hi],
            batch.wavelength_nm[lo:hi],
            batch.power_mw,
            batch.rays_per_unit,
        )
        parts.append(kernel.run(sub, n_coll[lo:hi], n_filt[lo:hi], lo))
    out = parts[0] if len(parts) == 1 else {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    return RayRecord(
        unit=batch.unit,
        status=out["status"].astype(np.int32),
        hit_mm=out["hit"].astype(float),
        passed=out["passed"].astype(bool),
        exit_direction=out["exit"].astype(float),
        wavelength_nm=batch.wavelength_nm,
        bounces=out["bounces"].astype(np.int32),
        power_mw=batch.power_mw,
        units=scene.units,
        rays_per_unit=batch.rays_per_unit or count // max(scene.units, 1),
        seconds=time.perf_counter() - start,
        variant=variant().variant,
    )


def trace(
    scene: IlluminationScene,
    source: LEDSource,
    rays: int,
    *,
    transmission: Transmission | None = None,
    seed: int = 0,
    max_bounces: int = DEFAULT_MAX_BOUNCES,
    msc: MitsubaScene | None = None,
) -> RayRecord:
    """Trace ``rays`` LED rays (split evenly over the units) through ``scene``.

    source: the LED (profile, spectrum, flux). transmission: the excitation filter's
    ``T(wavelength_nm, aoi_rad)`` (needed when the scene has a filter). seed: random seed (the
    same seed gives the same rays and the same fates). max_bounces: surfaces per ray before it
    is counted as truncated. msc: the scene already loaded with :func:`mitsuba_scene`.
    Timings (s) of sampling and tracing are in the record's ``timings``.
    """
    if rays < scene.units:
        raise ValueError(f"rays = {rays}: must be ≥ the number of LED units ({scene.units})")
    start = time.perf_counter()
    batch = emit_rays(scene, source, rays, seed)
    table = filter_table(scene, source, transmission)
    sampled = time.perf_counter()
    record = trace_rays(scene, batch, table, seed=seed, max_bounces=max_bounces, msc=msc)
    done = time.perf_counter()
    return dataclasses.replace(
        record, seconds=done - start, timings={"sample_s": sampled - start, "trace_s": done - sampled}
    )
