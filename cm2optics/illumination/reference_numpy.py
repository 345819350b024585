"""A plain NumPy reference tracer: the same scene, rays and physics, no acceleration structure.

It exists to check and to time the Mitsuba/Dr.Jit tracer (:mod:`.tracer`): it reads the same
:class:`~.geometry.IlluminationScene` parts, traces the same :class:`~.tracer.EmittedBatch`
and draws the same reflect/refract decisions (the TEA hash of ray index and step), so both
tracers must agree ray for ray up to floating-point rounding (float64 here, float32 there).

Intersections are brute force — Möller–Trumbore against every triangle of every part whose
bounding box the ray meets, in chunks — which is what "the naive way" costs; the benchmark
(``benchmarks/bench_illumination.py``) reports the ratio of the two tracers' speeds.
"""

from __future__ import annotations

import time

import numpy as np

from cm2optics.illumination.excitation import TransmissionTable
from cm2optics.illumination.geometry import IlluminationScene, Medium, Role
from cm2optics.illumination.tracer import (
    DEFAULT_MAX_BOUNCES,
    TEA_ROUNDS,
    EmittedBatch,
    RayRecord,
    Status,
    random_stream,
)
from cm2optics.optics.interfaces import fresnel_reflectance, refract, snell_cos_t
from cm2optics.optics.interfaces import reflect as mirror

__all__ = ["sample_tea_float32", "trace_rays_numpy"]

_PAIRS = 4_000_000  # ray × triangle pairs per chunk (memory bound)


def sample_tea_float32(v0: np.ndarray, v1: np.ndarray, rounds: int = TEA_ROUNDS) -> np.ndarray:
    """Mitsuba's ``sample_tea_float32``: TEA-encrypt (v0, v1) and map the top 23 bits of the second word to [0, 1)."""
    v0 = np.asarray(v0, dtype=np.uint32).copy()
    v1 = np.broadcast_to(np.asarray(v1, dtype=np.uint32), v0.shape).copy()
    total = np.uint32(0)
    with np.errstate(over="ignore"):
        for _ in range(rounds):
            total = np.uint32(total + np.uint32(0x9E3779B9))
            v0 += (
                ((v1 << np.uint32(4)) + np.uint32(0xA341316C))
                ^ (v1 + total)
                ^ ((v1 >> np.uint32(5)) + np.uint32(0xC8013EA4))
            )
            v1 += (
                ((v0 << np.uint32(4)) + np.uint32(0xAD90777D))
                ^ (v0 + total)
                ^ ((v0 >> np.uint32(5)) + np.uint32(0x7E95761E))
            )
    bits = (v1 >> np.uint32(9)) | np.uint32(0x3F800000)
    return bits.view(np.float32).astype(np.float64) - 1.0


class _Mesh:
    def __init__(self, part):
        tri = part.vertices_mm[part.faces]
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]
        normal = np.cross(self.e1, self.e2)
        self.normal = normal / np.linalg.norm(normal, axis=1, keepdims=True)
        self.corner = part.corner_normals
        self.lower = tri.reshape(-1, 3).min(axis=0) - 1e-6
        self.upper = tri.reshape(-1, 3).max(axis=0) + 1e-6
        self.code = part.code

    def box_hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t0 = (self.lower - o) * inv
            t1 = (self.upper - o) * inv
        near = np.nanmax(np.minimum(t0, t1), axis=1)
        far = np.nanmin(np.maximum(t0, t1), axis=1)
        return (far >= np.maximum(near, 0.0)) & np.isfinite(far)

    def intersect(self, o: np.ndarray, d: np.ndarray, tmin: np.ndarray):
        """Nearest hit of each ray beyond ``tmin``: t (inf if none), face, barycentrics u, v."""
        n, f = len(o), len(self.v0)
        best_t = np.full(n, np.inf)
        best_f = np.zeros(n, dtype=np.int64)
        best_u = np.zeros(n)
        best_v = np.zeros(n)
        step = max(1, _PAIRS // max(f, 1))
        for lo in range(0, n, step):
            oo, dd = o[lo : lo + step, None, :], d[lo : lo + step, None, :]
            p = np.cross(dd, self.e2[None])
            det = np.einsum("rfk,fk->rf", p, self.e1)
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / det
                s = oo - self.v0[None]
                u = np.einsum("rfk,rfk->rf", s, p) * inv
                q = np.cross(s, self.e1[None])
                v = np.einsum("rk,rfk->rf", dd[:, 0], q) * inv
                t = np.einsum("rfk,fk->rf", q, self.e2) * inv
            ok = (np.abs(det) > 1e-14) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > tmin[lo : lo + step, None])
            t = np.where(ok, t, np.inf)
            k = np.argmin(t, axis=1)
            rows = np.arange(len(k))
            best_t[lo : lo + step] = t[rows, k]
            best_f[lo : lo + step] = k
            best_u[lo : lo + step] = u[rows, k]
            best_v[lo : lo + step] = v[rows, k]
        return best_t, best_f, best_u, best_v


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _directions(d: np.ndarray, facing: np.ndarray, eta: np.ndarray, reflect: np.ndarray) -> np.ndarray:
    """Reflected (where ``reflect``) or refracted directions about the normals ``facing``."""
    ci = np.clip(-_dot(d, facing), 0.0, 1.0)[:, None]
    ct, _ = snell_cos_t(np, ci, eta[:, None])
    return np.where(reflect[:, None], mirror(d, facing, ci), refract(d, facing, eta[:, None], ci, ct))


def trace_rays_numpy(
    scene: IlluminationScene,
    batch: EmittedBatch,
    table: TransmissionTable,
    *,
    seed: int = 0,
    max_bounces: int = DEFAULT_MAX_BOUNCES,
) -> RayRecord:
    """Trace ``batch`` through ``scene`` with NumPy alone; same arguments and result as
    :func:`cm2optics.illumination.tracer.trace_rays`."""
    start = time.perf_counter()
    meshes = [_Mesh(part) for part in scene.parts]
    count = len(batch.unit)
    n_coll_all, n_filt_all = scene.refractive_indices(batch.wavelength_nm)
    status = np.zeros(count, dtype=np.int32)
    hit = np.full((count, 2), np.nan)
    passed = np.zeros(count, dtype=bool)
    exit_dir = np.full((count, 3), np.nan)
    bounces = np.zeros(count, dtype=np.int32)
    idx = np.arange(count)
    o = batch.origin_mm.astype(float).copy()
    d = batch.direction.astype(float).copy()
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    stream = random_stream(seed)
    depth = 0
    while idx.size:
        m = idx.size
        eps = 1e-7 * (1.0 + np.abs(o).max(axis=1))
        best_t = np.full(m, np.inf)
        best_mesh = np.full(m, -1)
        best_face = np.zeros(m, dtype=np.int64)
        best_u = np.zeros(m)
        best_v = np.zeros(m)
        for k, mesh in enumerate(meshes):
            sel = np.flatnonzero(mesh.box_hit(o, d))
            if sel.size == 0:
                continue
            t, f, u, v = mesh.intersect(o[sel], d[sel], eps[sel])
            better = t < best_t[sel]
            rows = sel[better]
            best_t[rows], best_mesh[rows], best_face[rows] = t[better], k, f[better]
            best_u[rows], best_v[rows] = u[better], v[better]
        valid = np.isfinite(best_t)
        new_status = np.where(valid, int(Status.ACTIVE), int(Status.ESCAPED))
        code = np.zeros(m, dtype=np.int64)
        ng = np.zeros((m, 3))
        ns = np.zeros((m, 3))
        for k, mesh in enumerate(meshes):
            rows = np.flatnonzero(valid & (best_mesh == k))
            if rows.size == 0:
                continue
            f = best_face[rows]
            code[rows] = mesh.code
            ng[rows] = mesh.normal[f]
            if mesh.corner is None:
                ns[rows] = mesh.normal[f]
            else:
                u, v = best_u[rows, None], best_v[rows, None]
                c = mesh.corner[f]
                smooth = (1 - u - v) * c[:, 0] + u * c[:, 1] + v * c[:, 2]
                ns[rows] = smooth / np.linalg.norm(smooth, axis=1, keepdims=True)
        role, medium, group = code & 15, (code >> 4) & 15, code >> 8
        point = o + np.where(valid, best_t, 0.0)[:, None] * d
        ns = np.where((_dot(ns, ng) < 0)[:, None], -ns, ns)
        entering = _dot(d, ng) < 0
        n_solid = np.where(medium == int(Medium.FILTER), n_filt_all[idx], n_coll_all[idx])
        n1 = np.where(entering, 1.0, n_solid)
        n2 = np.where(entering, n_solid, 1.0)
        eta = n1 / n2
        face_g = np.where(entering[:, None], ng, -ng)
        face_s = np.where(entering[:, None], ns, -ns)
        face_s = np.where((_dot(d, face_s) < 0)[:, None], face_s, face_g)
        cos_i = np.clip(-_dot(d, face_s), 0.0, 1.0)
        sin_i = np.sqrt(np.maximum(1 - cos_i**2, 0.0))
        cos_t, tir = snell_cos_t(np, cos_i, eta)
        with np.errstate(divide="ignore", invalid="ignore"):
            reflectance = fresnel_reflectance(cos_i, cos_t, n1, n2)
        coated = role == int(Role.COATED)
        aoi_air = np.arcsin(np.minimum(np.where(entering, sin_i, n_solid * sin_i), 1.0))
        if coated.any():
            reflectance = np.where(coated, 1.0 - table(batch.wavelength_nm[idx], aoi_air), reflectance)
        reflectance = np.where(role == int(Role.GLASS), 0.0, reflectance)
        reflectance = np.where(tir, 1.0, reflectance)
        reflect = sample_tea_float32(idx.astype(np.uint32), np.uint32((stream + depth) % 2**32)) < reflectance

        new_d = _directions(d, face_s, eta, reflect)
        side = _dot(new_d, face_g)
        wrong = np.where(reflect, side <= 0, side >= 0)
        cos_g = _dot(d, face_g)
        reflect_g = reflect | snell_cos_t(np, cos_g, eta)[1]
        new_d = np.where(wrong[:, None], _directions(d, face_g, eta, reflect_g), new_d)
        reflect = np.where(wrong, reflect_g, reflect)
        portal = role == int(Role.PORTAL)
        new_d = np.where(portal[:, None], d, new_d)
        new_d /= np.linalg.norm(new_d, axis=1, keepdims=True)

        leaving_filter = (role == int(Role.GLASS)) & ~entering & ~reflect
        crossing = valid & ((portal & (_dot(d, ng) > 0)) | leaving_filter) & ~passed[idx]
        passed[idx[crossing]] = True
        exit_dir[idx[crossing]] = new_d[crossing]  # in the air, after the portal or the filter
        absorbed = valid & (role == int(Role.ABSORBER))
        new_status = np.where(absorbed, int(Status.ABSORBED) + group, new_status)
        landed = valid & (role == int(Role.SAMPLE))
        new_status = np.where(landed, int(Status.SAMPLE), new_status)
        hit[idx[landed]] = point[landed, :2]
        alive = valid & ~absorbed & ~landed
        truncated = alive & (depth + 1 >= max_bounces)
        new_status = np.where(truncated, int(Status.TRUNCATED), new_status)
        done = new_status != int(Status.ACTIVE)
        status[idx[done]] = new_status[done]
        bounces[idx[done]] = depth + 1
        # Leave the surface on the side the new direction points to.
        offset = np.sign(_dot(new_d, ng))[:, None] * ng * (1e-7 * (1.0 + np.abs(point).max(axis=1)))[:, None]
        keep = ~done
        o = (point + offset)[keep]
        d = new_d[keep]
        idx = idx[keep]
        depth += 1
    return RayRecord(
        unit=batch.unit,
        status=status,
        hit_mm=hit,
        passed=passed,
        exit_direction=exit_dir,
        wavelength_nm=batch.wavelength_nm,
        bounces=bounces,
        power_mw=batch.power_mw,
        units=scene.units,
        rays_per_unit=batch.rays_per_unit or count // max(scene.units, 1),
        seconds=time.perf_counter() - start,
        variant="numpy-reference",
    )
