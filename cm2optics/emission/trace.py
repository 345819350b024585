"""Exact, vectorised ray trace of the emission path: point source → filter → mask → lenslet → film → sensor.

Every ray leaves a source point with direction ``(u, v, −1)/√(1 + u² + v²)`` (``u, v`` the
direction tangents; the light goes towards the device, −z) and is aimed at one lenslet. All
rays of a call — any mix of sources, lenslets and wavelength bands — advance together through
the same surfaces, in closed form (plane and sphere intersections, Snell's law in vector form):

1. the emission filter, a plane-parallel plate of the design's glass (rays outside the plate
   hit the housing);
2. air, through the mask's opening and the housing bore (the MLA's corner tabs included);
3. the lenslet's sphere (centre ``radius_mm`` below the vertex); the hit must lie inside the
   lenslet's clear aperture (its cell, as on a 100 %-fill-factor array);
4. the PMMA down to the flat face, which the ray must leave through (not the array's sides;
   no total internal reflection);
5. air, through the spacer between the array and the film (nothing else lies under the array);
6. the film (gelatin plate), if the design has one; rays outside it meet its opaque seat;
7. air to the sensor plane z = 0; the ray must land on the active area.

A tilted array (``optics.mla_tilt``) is traced in its own frame (steps 3–4: the rays turned
into it and back); a tilted sensor (``optics.sensor_tilt``) is met as its plane, and the landing
point and direction are returned in its own axes (x, y along it; z along its normal).

Optical path lengths are summed in float64 (they feed the wavefront, :mod:`.wavefront`);
refractive indices are per ray (each ray carries its band's wavelength). The ray keeps its
geometry even where it is blocked, so that the pupil mapping stays smooth: ``traced`` says the
geometry exists (no sphere miss, no TIR), ``passed`` that nothing blocked the ray.

Engines (``engine``):

* ``"drjit"`` (default where Mitsuba has a JIT variant): the trace is recorded on Dr.Jit
  float64 arrays and runs as one compiled kernel (LLVM on every CPU core, or CUDA), and the
  housing is a Mitsuba scene of meshes (:mod:`.housing`) that the air segments are tested
  against (``scene.ray_test``);
* ``"numpy"``: the same code on NumPy arrays, with the housing's openings tested in closed
  form. Used as the reference in the tests and where no JIT variant exists.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from cm2optics.emission.optics import EmissionOptics
from cm2optics.optics.arrays import DrJitOps, NumpyOps
from cm2optics.optics.backend import is_jit, mitsuba
from cm2optics.optics.interfaces import fresnel_transmittance, refract, snell_cos_t
from cm2optics.optics.tilt import rotate

__all__ = ["ENGINES", "RayBatch", "TracedRays", "default_engine", "trace_rays"]

ENGINES = ("drjit", "numpy")


@dataclass(frozen=True, eq=False)
class RayBatch:
    """Rays to trace: launch tangents per ray, and what rays share (source, lenslet, wavelength)
    per ray or per group of rays.

    source_mm: (g, 3) source point in the device frame, mm.
    u, v: (n,) direction tangents d_x/|d_z|, d_y/|d_z| of the ray leaving the source.
    lenslet: (g,) index into :attr:`EmissionOptics.lenslets` of the lenslet the ray is aimed at.
    n_filter, n_lens, n_film: (g,) refractive indices of the filter glass, the lens and the film
        at the ray's wavelength.
    group: (n,) row of the (g,) arrays that each ray takes (None: one row per ray, g = n). Groups
        keep the per-ray data small: the Dr.Jit kernel gathers a ray's row itself.
    """

    source_mm: np.ndarray
    u: np.ndarray
    v: np.ndarray
    lenslet: np.ndarray
    n_filter: np.ndarray
    n_lens: np.ndarray
    n_film: np.ndarray
    group: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.u)


@dataclass(frozen=True, eq=False)
class TracedRays:
    """The traced rays (NumPy arrays, one value per ray).

    traced: the geometry exists down to the sensor plane (no sphere miss, no TIR).
    passed: traced and not blocked by any aperture, the housing or the sensor's edge.
    x_mm, y_mm: where the ray meets the sensor plane (device frame), mm.
    direction: (n, 3) unit direction of the last segment (in air, towards −z).
    opl_mm: optical path length from the source to the sensor plane, mm.
    aoi_filter_rad, aoi_film_rad: angles of incidence (in air) at the filter and the film, rad.
    fresnel: unpolarised power transmittance of the lens's two faces (sphere in, flat face out).
    """

    traced: np.ndarray
    passed: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    direction: np.ndarray
    opl_mm: np.ndarray
    aoi_filter_rad: np.ndarray
    aoi_film_rad: np.ndarray
    fresnel: np.ndarray


_WARNED = False


def default_engine() -> str:
    """``"drjit"`` when Mitsuba runs a JIT variant (LLVM/CUDA), else ``"numpy"`` (warned once)."""
    global _WARNED
    if is_jit():
        return "drjit"
    if not _WARNED:
        _WARNED = True
        warnings.warn(
            "emission: no JIT variant of Mitsuba (LLVM ≥ 17 or CUDA) is available; tracing with NumPy "
            "(several times slower). Install LLVM ≥ 17 (Debian/Ubuntu: apt install libllvm19).",
            RuntimeWarning,
            stacklevel=2,
        )
    return "numpy"


def _refract(ops: Any, dx: Any, dy: Any, dz: Any, nx: Any, ny: Any, nz: Any, eta: Any):
    """Snell's law, one component at a time: unit direction d through a surface of unit normal n
    facing the incoming ray (n·d < 0), index ratio eta = n₁/n₂. Returns (tx, ty, tz, cos_i,
    cos_t, ok); ok False on TIR."""
    cos_i = -(dx * nx + dy * ny + dz * nz)
    cos_t, _ = snell_cos_t(ops, cos_i, eta)
    tx, ty, tz = (refract(d, n, eta, cos_i, cos_t) for d, n in ((dx, nx), (dy, ny), (dz, nz)))
    return tx, ty, tz, cos_i, cos_t, cos_t > 0.0


def _inside(ops: Any, x: Any, y: Any, x0: Any, x1: Any, y0: Any, y1: Any) -> Any:
    return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)


def _bores_between(
    optics: EmissionOptics, z_low: float, z_high: float
) -> list[tuple[float, float, float, float, float]]:
    """(half_x, half_y, diagonal, z_a, z_b) of the bores overlapping the height range [z_low, z_high]."""
    out = []
    for bore in optics.bores:
        a, b = max(z_low, bore.z0_mm), min(z_high, bore.z1_mm)
        if b > a:
            out.append((bore.half_x_mm, bore.half_y_mm, bore.diagonal_mm, a, b))
    return out


def _trace(ops: Any, optics: EmissionOptics, r: dict[str, Any], test_segment: Any) -> dict[str, Any]:
    """The trace itself, written once for NumPy and Dr.Jit arrays (see the module docstring).

    ``test_segment(px, py, pz, dx, dy, dz, length, z_low, z_high)`` returns True where the air
    segment from p, ``length`` mm along d (downwards), clears the housing; ``z_low``–``z_high``
    (mm) bound the heights the segments of that stretch of the path can reach."""
    sx, sy, sz = r["sx"], r["sy"], r["sz"]
    norm = ops.sqrt(1.0 + r["u"] * r["u"] + r["v"] * r["v"])
    dx, dy, dz = r["u"] / norm, r["v"] / norm, -1.0 / norm
    aoi_filter_cos = -dz

    filt = optics.filter
    # 1. Filter top face.
    t = (filt.z1_mm - sz) / dz
    px, py, pz = sx + t * dx, sy + t * dy, ops.full(filt.z1_mm, sx)
    opl = t
    passed = _inside(ops, px, py, -filt.half_x_mm, filt.half_x_mm, -filt.half_y_mm, filt.half_y_mm)
    # Inside the glass.
    gx, gy, gz, _, _, ok = _refract(ops, dx, dy, dz, 0.0, 0.0, 1.0, 1.0 / r["n_filter"])
    traced = ok
    t = (filt.z0_mm - filt.z1_mm) / gz
    px, py, pz = px + t * gx, py + t * gy, ops.full(filt.z0_mm, sx)
    opl = opl + r["n_filter"] * t
    passed = passed & _inside(ops, px, py, -filt.half_x_mm, filt.half_x_mm, -filt.half_y_mm, filt.half_y_mm)
    # Out of the glass: the original direction (parallel faces).

    # 3. The lenslet's sphere (in the array's own frame where it is tilted).
    px0, py0, pz0, dx0, dy0, dz0 = px, py, pz, dx, dy, dz
    if optics.mla_tilt:
        px, py, pz = rotate(optics.mla_tilt, px, py, pz, optics.mla_pivot_mm, inverse=True)
        dx, dy, dz = rotate(optics.mla_tilt, dx, dy, dz, inverse=True)
    radius = optics.radius_mm
    cx, cy, cz = r["cx"], r["cy"], optics.vertex_z_mm - radius
    ox, oy, oz = px - cx, py - cy, pz - cz
    b = dx * ox + dy * oy + dz * oz
    c = ox * ox + oy * oy + oz * oz - radius * radius
    disc = b * b - c
    traced = traced & (disc >= 0.0)
    t = -b - ops.sqrt(ops.maximum(disc, 0.0))
    hx, hy, hz = px + t * dx, py + t * dy, pz + t * dz
    opl = opl + t
    passed = passed & test_segment(px0, py0, pz0, dx0, dy0, dz0, t, optics.land_z_mm, filt.z0_mm)
    passed = passed & _inside(ops, hx, hy, r["ax0"], r["ax1"], r["ay0"], r["ay1"])
    nx, ny, nz = (hx - cx) / radius, (hy - cy) / radius, (hz - cz) / radius
    n_lens = r["n_lens"]
    lx, ly, lz, cos_i, cos_t, ok = _refract(ops, dx, dy, dz, nx, ny, nz, 1.0 / n_lens)
    traced = traced & ok
    fresnel = fresnel_transmittance(cos_i, cos_t, 1.0, n_lens)

    # 4. Down through the PMMA to the flat face.
    t = (optics.flat_z_mm - hz) / lz
    px, py, pz = hx + t * lx, hy + t * ly, ops.full(optics.flat_z_mm, sx)
    opl = opl + n_lens * t
    (x0, x1), (y0, y1) = optics.mla_x_mm, optics.mla_y_mm
    passed = passed & _inside(ops, px, py, x0, x1, y0, y1)
    ex, ey, ez, cos_i, cos_t, ok = _refract(ops, lx, ly, lz, 0.0, 0.0, 1.0, n_lens)
    traced = traced & ok
    fresnel = fresnel * fresnel_transmittance(cos_i, cos_t, n_lens, 1.0)
    if optics.mla_tilt:  # back to the device frame
        px, py, pz = rotate(optics.mla_tilt, px, py, pz, optics.mla_pivot_mm)
        ex, ey, ez = rotate(optics.mla_tilt, ex, ey, ez)
    aoi_film_cos = -ez

    # 5-6. Air to the film, through it, and on to the sensor.
    film = optics.film
    if film is not None:
        t = (film.z1_mm - pz) / ez
        qx, qy = px + t * ex, py + t * ey
        opl = opl + t
        passed = passed & test_segment(px, py, pz, ex, ey, ez, t, film.z1_mm, optics.flat_z_mm)
        passed = passed & _inside(ops, qx, qy, -film.half_x_mm, film.half_x_mm, -film.half_y_mm, film.half_y_mm)
        fx, fy, fz, _, _, ok = _refract(ops, ex, ey, ez, 0.0, 0.0, 1.0, 1.0 / r["n_film"])
        traced = traced & ok
        t = (film.z0_mm - film.z1_mm) / fz
        qx, qy = qx + t * fx, qy + t * fy
        opl = opl + r["n_film"] * t
        passed = passed & _inside(ops, qx, qy, -film.half_x_mm, film.half_x_mm, -film.half_y_mm, film.half_y_mm)
        px, py, pz = qx, qy, ops.full(film.z0_mm, sx)
    else:
        passed = passed & test_segment(px, py, pz, ex, ey, ez, -pz / ez, 0.0, optics.flat_z_mm)
    # 7. The sensor: the plane z = 0, or its tilted plane n·p = 0 read in its own axes.
    if optics.sensor_tilt:
        (n0,), (n1,), (n2,) = (row[2:] for row in optics.sensor_tilt)  # its normal: R's third column
        t = -(n0 * px + n1 * py + n2 * pz) / (n0 * ex + n1 * ey + n2 * ez)
        px, py, pz = px + t * ex, py + t * ey, pz + t * ez
        px, py, _ = rotate(optics.sensor_tilt, px, py, pz, inverse=True)
        ex, ey, ez = rotate(optics.sensor_tilt, ex, ey, ez, inverse=True)
    else:
        t = -pz / ez
        px, py = px + t * ex, py + t * ey
    opl = opl + t
    sh_x, sh_y = optics.sensor_half_x_mm, optics.sensor_half_y_mm
    passed = passed & _inside(ops, px, py, -sh_x, sh_x, -sh_y, sh_y) & traced
    return {
        "traced": traced,
        "passed": passed,
        "x": px,
        "y": py,
        "dx": ex,
        "dy": ey,
        "dz": ez,
        "opl": opl,
        "cos_filter": aoi_filter_cos,
        "cos_film": aoi_film_cos,
        "fresnel": fresnel,
    }


#: Columns of a ray group's row: source (3), lenslet vertex (2), clear aperture (4), indices (3).
_GROUP_COLUMNS = ("sx", "sy", "sz", "cx", "cy", "ax0", "ax1", "ay0", "ay1", "n_filter", "n_lens", "n_film")


def _groups(optics: EmissionOptics, rays: RayBatch) -> tuple[np.ndarray, np.ndarray]:
    """The (g, 12) table of the rays' groups (:data:`_GROUP_COLUMNS`) and each ray's row (n,)."""
    lenslet = np.asarray(rays.lenslet, dtype=np.int64).reshape(-1)
    table = np.array(
        [[c.vertex_x_mm, c.vertex_y_mm, c.x0_mm, c.x1_mm, c.y0_mm, c.y1_mm] for c in optics.lenslets], dtype=float
    )
    if lenslet.size and (lenslet.min() < 0 or lenslet.max() >= len(table)):
        raise ValueError(f"lenslet indices must lie within 0–{len(table) - 1}")
    g = len(lenslet)
    source = np.asarray(rays.source_mm, dtype=float)
    if source.shape != (g, 3):
        raise ValueError(f"source_mm has shape {source.shape}: must be ({g}, 3), one row per lenslet entry")
    indices = [np.asarray(a, dtype=float).reshape(-1) for a in (rays.n_filter, rays.n_lens, rays.n_film)]
    if any(len(a) != g for a in indices):
        raise ValueError(f"n_filter, n_lens and n_film must have {g} entries, as lenslet")
    n = len(rays.u)
    if len(rays.v) != n:
        raise ValueError(f"u and v must have the same length (got {n} and {len(rays.v)})")
    if rays.group is None:
        if g != n:
            raise ValueError(f"without groups every per-ray array needs {n} entries (lenslet has {g})")
        group = np.arange(n)
    else:
        group = np.asarray(rays.group, dtype=np.int64).reshape(-1)
        if len(group) != n or (n and (group.min() < 0 or group.max() >= g)):
            raise ValueError(f"group must hold {n} row indices within 0–{g - 1}")
    rows = np.column_stack([source, table[lenslet], *indices]) if g else np.zeros((0, len(_GROUP_COLUMNS)))
    return rows, group


def _per_ray(optics: EmissionOptics, rays: RayBatch) -> dict[str, np.ndarray]:
    """One array per ray and quantity (the NumPy engine)."""
    rows, group = _groups(optics, rays)
    per = rows[group]
    out = {name: per[:, k] for k, name in enumerate(_GROUP_COLUMNS)}
    out["u"], out["v"] = np.asarray(rays.u, dtype=float), np.asarray(rays.v, dtype=float)
    return out


def _analytic_segment_test(ops: Any, optics: EmissionOptics):
    """Closed-form housing test: a straight segment stays inside a (convex) bore over a height
    range exactly when it is inside at both ends of that range."""

    def test(px, py, pz, dx, dy, dz, length, z_low, z_high):
        ok = None
        for half_x, half_y, diagonal, a, b in _bores_between(optics, z_low, z_high):
            for z in (a, b):
                t = (z - pz) / dz
                x, y = px + t * dx, py + t * dy
                inside = _inside(ops, x, y, -half_x, half_x, -half_y, half_y)
                if math.isfinite(diagonal):
                    inside = inside & (ops.abs(x) + ops.abs(y) <= diagonal)
                ok = inside if ok is None else ok & inside
        return ok if ok is not None else (px == px)

    return test


#: Alignment (bytes) of the arrays handed to Dr.Jit: one vector of 16 float64.
_ALIGN = 128


def _aligned(arrays: list[np.ndarray], dtype: type = np.float64) -> list[np.ndarray]:
    """Copies of 1-D ``arrays`` (any lengths) as ``dtype``, each starting on a :data:`_ALIGN`-byte
    boundary.

    Dr.Jit reads NumPy memory in place and compiles its loads as aligned or not from the
    address it gets: arrays from ``malloc`` land on either, so a kernel's hash (and an LLVM
    compile of 30–50 ms) would change from one call to the next. Aligned inputs give one kernel
    per shape of the trace, compiled once per process (and cached on disk across processes)."""
    size = np.dtype(dtype).itemsize
    per = _ALIGN // size
    strides = [-(-len(a) // per) * per for a in arrays]
    buffer = np.empty(sum(strides) + per, dtype=dtype)
    start = (-buffer.ctypes.data % _ALIGN) // size
    out = []
    for values, stride in zip(arrays, strides, strict=True):
        view = buffer[start : start + len(values)]
        view[:] = values
        out.append(view)
        start += stride
    return out


def _aligned_uint32(values: np.ndarray) -> np.ndarray:
    """An aligned uint32 copy of ``values`` (see :func:`_aligned`)."""
    return _aligned([np.asarray(values)], np.uint32)[0]


def _numpy(value: Any) -> np.ndarray:
    return value.numpy() if hasattr(value, "numpy") else np.asarray(value)


def _result(arrays: dict[str, Any]) -> TracedRays:
    a = {k: _numpy(v) for k, v in arrays.items()}
    return TracedRays(
        traced=a["traced"].astype(bool, copy=False),
        passed=a["passed"].astype(bool, copy=False),
        x_mm=a["x"],
        y_mm=a["y"],
        direction=np.stack([a["dx"], a["dy"], a["dz"]], axis=1),
        opl_mm=a["opl"],
        aoi_filter_rad=np.arccos(np.clip(a["cos_filter"], -1.0, 1.0)),
        aoi_film_rad=np.arccos(np.clip(a["cos_film"], -1.0, 1.0)),
        fresnel=np.nan_to_num(a["fresnel"]),
    )


def trace_rays(optics: EmissionOptics, rays: RayBatch, engine: str | None = None) -> TracedRays:
    """Trace ``rays`` through ``optics`` (see the module docstring) on ``engine``
    (``"drjit"`` or ``"numpy"``; default :func:`default_engine`)."""
    engine = engine or default_engine()
    if engine not in ENGINES:
        raise ValueError(f"engine = {engine!r}: must be one of {', '.join(ENGINES)}")
    if len(rays) == 0:
        _groups(optics, rays)
        empty = np.zeros(0)
        return TracedRays(
            empty.astype(bool), empty.astype(bool), empty, empty, np.zeros((0, 3)), empty, empty, empty, empty
        )
    if engine == "numpy" or not is_jit():
        if engine == "drjit":
            raise ValueError("engine = 'drjit' needs a JIT variant of Mitsuba (LLVM ≥ 17 or CUDA)")
        per = _per_ray(optics, rays)
        ops = NumpyOps()
        with np.errstate(invalid="ignore", divide="ignore"):
            return _result(_trace(ops, optics, per, _analytic_segment_test(ops, optics)))
    from cm2optics.emission.housing import housing_scene, segment_test

    rows, group = _groups(optics, rays)
    ops = DrJitOps()
    dr, mi = ops.dr, mitsuba()
    u, v, table = _aligned([np.asarray(rays.u, float), np.asarray(rays.v, float), rows.ravel()])
    index = mi.UInt32(_aligned_uint32(group)) * len(_GROUP_COLUMNS)
    table = ops.Float64(table)
    r = {name: dr.gather(ops.Float64, table, index + k) for k, name in enumerate(_GROUP_COLUMNS)}
    r["u"], r["v"] = ops.Float64(u), ops.Float64(v)
    out = _trace(ops, optics, r, segment_test(housing_scene(optics)))
    ops.dr.eval(*out.values())
    return _result(out)


def paraxial_reach_mm(optics: EmissionOptics, source_z_mm: float, n_filter: float, z_mm: float) -> float:
    """Reduced distance (mm) from a source at height ``source_z_mm`` down to height ``z_mm`` below
    the filter: the filter's thickness counts as t/n (the plate's paraxial effect)."""
    t = optics.filter.thickness_mm
    return (source_z_mm - z_mm) - t + t / n_filter if math.isfinite(n_filter) else source_z_mm - z_mm
