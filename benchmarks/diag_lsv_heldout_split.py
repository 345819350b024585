"""Diagnostic (issue 13, session 14; figures in BENCHMARKS.md): split of the held-out emitter error: per emitter of the bench's draw
(seed 0, radii 0,1,2,3, --per-radius N), against the traced emitter t/u (as the bench):

  truth   : the scan's own synthetic ePSF AT THE EMITTER (cm2 psf simulate --positions, epsf.h5),
            cropped in the model's frame, placed at the emitter's focus  -> sub-pixel phase + window floor
  proj    : that truth projected on the model's basis (per lenslet for a per-lenslet model)  -> + low rank
  model   : model.point_image (interpolated coefficients)  -> + shape change between nodes (interpolation)

Steps: `positions` writes the CSV; `truth` needs the truth scan; `abm` refits the aberration model
on scan9 and renders it at the emitters (full rank, projected) and on node grids of spacing H
(trilinear blend of chief-ray-registered renders).

usage: split.py positions N OUT.csv
       split.py truth N TRUTHSCAN OUT.json NAME=MODEL ...
       split.py abm N TRUTHSCAN OUT.json MODEL SCAN9 [n_sweep_per_radius]
"""

import importlib.util
import json
import math
import sys
import time
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch

torch.set_num_threads(1)

from cm2optics.lsv.validate import image_errors  # noqa: E402

spec = importlib.util.spec_from_file_location("bench", Path(__file__).with_name("bench_lsv_heldout.py"))
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def positions(n):
    args = Namespace(seed=0, radii="0,1,2,3", per_radius=n, angles_deg="0,360", patch_center_mm=None)
    return bench.emitters(args, (-0.5, 0.5))


def place(model, patches, pos):
    """Image of fine patches (J, hS, wS) in the model's chief-ray frame, placed at pos's foci as
    the model places its own (:func:`cm2optics.lsv.sparse.place_patches`)."""
    from cm2optics.lsv.sparse import place_patches

    return place_patches(model, patches, *pos)


def projector(model):
    """x (J, hS, wS) -> least-squares projection on the model's basis (per lenslet if block-diagonal)."""
    B = model.basis
    J = B.shape[1]
    blocks = [model.lenslet_terms(j) for j in range(J)]
    per_lenslet = sum(len(b) for b in blocks) == len(B) and all(len(b) < len(B) for b in blocks)
    if per_lenslet:
        return model.project, "per lenslet"
    Bf = B.reshape(len(B), -1).astype(np.float64)
    Ginv = np.linalg.pinv(Bf @ Bf.T)

    def project(x):
        return (Bf.T @ (Ginv @ (Bf @ x.reshape(-1)))).reshape(x.shape)

    return project, "one basis of focus arrays"


_EMISSION = {}


def truth_crops(model, pts):
    """(len(pts), J, hS, wS) the traced ePSFs at pts (what cm2 psf simulate --oversample 4 writes to
    epsf.h5 for a 2-um isotropic bead, photons per emitted photon), registered as epsf_crops does."""
    from cm2optics.design import load_preset
    from cm2optics.emission.psf import EmissionModel, PSFSettings
    from cm2optics.emission.source import fluorescent_bead
    from cm2optics.lsv.kernels import sample_window

    if "m" not in _EMISSION:
        _EMISSION["m"] = EmissionModel(
            load_preset("cm2-v2"), fluorescent_bead(2.0), settings=PSFSettings(binning=2, oversample=4)
        )
    em = _EMISSION["m"]
    S = model.oversample
    h, w = model.patch_shape
    J = model.n_lenslets
    out = np.zeros((len(pts), J, h * S, w * S))
    for n, p in enumerate(pts):
        foci = em.foci(np.asarray(p, float))
        r0 = min(f.row0 for f in foci) * S
        c0 = min(f.col0 for f in foci) * S
        r1 = max(f.row0 * S + f.epsf.shape[0] for f in foci)
        c1 = max(f.col0 * S + f.epsf.shape[1] for f in foci)
        canvas = np.zeros((r1 - r0, c1 - c0))
        for f in foci:
            canvas[
                f.row0 * S - r0 : f.row0 * S - r0 + f.epsf.shape[0], f.col0 * S - c0 : f.col0 * S - c0 + f.epsf.shape[1]
            ] += f.epsf
        centres = model.geometry.focus(*p)
        for j in range(J):
            out[n, j] = sample_window(canvas, (centres[j, 0] * S - r0, centres[j, 1] * S - c0), (h * S, w * S))
    return out


def traced_all(pts):
    from cm2optics.design import load_preset

    design = load_preset("cm2-v2")
    out = []
    for p in pts:
        out.append(bench.traced(design, 2, p, 2.0, False, None))
    return out


def summary(rows, keys):
    groups = {}
    for r in rows:
        groups.setdefault(r["group"], []).append(r)
    out = {}
    for g, members in groups.items():
        out[g] = {"n": len(members)}
        for k in keys:
            vals = [m[k]["error"] for m in members if k in m]
            shp = [m[k]["shape_error"] for m in members if k in m]
            flux = [m[k]["flux_ratio"] for m in members if k in m]
            if vals:
                out[g][k] = {
                    "error": float(np.mean(vals)),
                    "error_min": float(np.min(vals)),
                    "error_max": float(np.max(vals)),
                    "shape_error": float(np.mean(shp)),
                    "flux_ratio": float(np.mean(flux)),
                }
    return out


def cache_pupils():
    """Trace the design's pupils once for the several aberration-model fits of one run."""
    import cm2optics.calibrate.aberration_build as ab

    original, cache = ab.trace_pupils, {}

    def cached(emission, pos, seed=0, progress=None):
        if "p" not in cache:
            cache["p"] = original(emission, pos, seed=seed, progress=progress)
        return cache["p"]

    ab.trace_pupils = cached


def fit_both_placements(design, crops, index, positions9, fit_nodes, zs, model):
    """The aberration model fitted twice on ``fit_nodes``: its placement from the fine ePSF crops
    and from the whole-pixel windows (each at its own sub-pixel phase). Returns (fine, pixel, record)."""
    from cm2optics.calibrate.aberration_build import _fit_lenslets
    from cm2optics.lsv.epsf_estimate import pixel_windows

    S, pixel_um = model.oversample, index.meta.pixel_um
    t0 = time.time()
    fine, record = _fit_lenslets(design, crops, positions9, fit_nodes, zs, model.geometry, S, pixel_um, 0, None)
    print(f"fit (fine crops, {len(fit_nodes)} nodes) {time.time() - t0:.0f} s", record, flush=True)
    t0 = time.time()
    windows, foci = pixel_windows(index, model.geometry, model.patch_shape)
    phases = foci - np.floor(foci)
    pixel, _ = _fit_lenslets(
        design, windows, positions9, fit_nodes, zs, model.geometry, S, pixel_um, 0, None, phases=phases
    )
    print(f"fit (whole-pixel windows) {time.time() - t0:.0f} s", flush=True)
    return fine, pixel, record


def placement_difference(fine, pixel, emitter_positions):
    """Per lenslet, how far the whole-pixel placement's offset (µm) and flux differ from the fine one's."""
    from cm2optics.emission.aberration_model import placement_features

    F = placement_features(np.asarray(emitter_positions))
    difference = {}
    for j in fine:
        if fine[j] is not None and pixel.get(j) is not None:
            d = F @ pixel[j].offset - F @ fine[j].offset
            r = np.exp(F @ pixel[j].log_flux - F @ fine[j].log_flux)
            difference[j] = {
                "mean_offset_diff_um": float(np.linalg.norm(d, axis=1).mean() * 1e3),
                "max_offset_diff_um": float(np.linalg.norm(d, axis=1).max() * 1e3),
                "flux_ratio_mean": float(r.mean()),
                "flux_ratio_std": float(r.std()),
            }
    print("pixel vs fine placement at the emitters", difference, flush=True)
    return difference


def renderer(model, lenslet_models):
    """The fitted lenslet models' fine PSFs at a point, in the model's focus-patch layout."""

    def render(p):
        out = np.zeros((model.n_lenslets, *model.basis.shape[2:]))
        for j, lm in lenslet_models.items():
            if lm is not None:
                out[j] = lm.predict(p)
        return out

    return render


def main_truth(n, truthscan, out_json, specs):
    from cm2optics.lsv.model import load_model

    em = positions(n)
    pts = [(0.0, 0.0, 0.0)] + [p for _, _, p in em]
    t0 = time.time()
    traced = traced_all(pts)
    u = float(traced[0].sum())
    print(f"traced {len(pts)} in {time.time() - t0:.0f} s", flush=True)
    rows = [{"group": g, "r_mm": r, "position_mm": p} for g, r, p in em]
    info = {}
    for spec_ in specs:
        name, _, path = spec_.partition("=")
        t0 = time.time()
        model = load_model(path)
        crops = truth_crops(model, pts)
        print(f"truth crops {time.time() - t0:.0f} s", flush=True)
        s0 = place(model, crops[0], pts[0]).sum()
        project, kind = projector(model)
        info[name] = {
            "path": path,
            "rank": int(model.rank),
            "basis": kind,
            "patch_shape": list(model.patch_shape),
            "s0_truth_units": float(s0),
        }
        m0 = model.point_image(*pts[0])
        info[name]["model_total_at_unit_point"] = float(m0.sum())
        for i, (g, _r, p) in enumerate(em):
            t = traced[i + 1] / u
            truth = crops[i + 1] / s0
            rows[i][f"{name}:truth"] = image_errors(place(model, truth, p), t)
            rows[i][f"{name}:proj"] = image_errors(place(model, project(truth), p), t)
            rows[i][f"{name}:model"] = image_errors(model.point_image(*p), t)
            print(
                name,
                g,
                p,
                " ".join(f"{k} {rows[i][f'{name}:{k}']['error']:.3f}" for k in ("truth", "proj", "model")),
                flush=True,
            )
        info[name]["seconds"] = time.time() - t0
        del model, crops
    keys = [k for k in rows[0] if ":" in k]
    json.dump({"info": info, "summary": summary(rows, keys), "rows": rows}, open(out_json, "w"), indent=1)
    for g, v in summary(rows, keys).items():
        print(g, v["n"], " ".join(f"{k} {v[k]['error']:.3f}" for k in keys))


def main_abm(n, truthscan, out_json, model_path, scan9, n_sweep):
    def dump(rows, info):
        keys = sorted({k for r in rows for k in r if ":" in k})
        json.dump(
            {"info": info, "summary": summary(rows, keys), "rows": rows}, open(out_json, "w"), indent=1, default=str
        )

    from cm2optics.design import load_preset
    from cm2optics.formats.scan import open_scan
    from cm2optics.lsv.epsf import epsf_crops
    from cm2optics.lsv.model import load_model

    design = load_preset("cm2-v2")
    em = positions(n)
    pts = [(0.0, 0.0, 0.0)] + [p for _, _, p in em]
    model = load_model(model_path)
    S = model.oversample
    index9 = open_scan(scan9)
    t0 = time.time()
    crops9 = np.asarray(epsf_crops(index9, model.geometry, model.patch_shape, S))
    print(f"scan9 crops {crops9.shape} {time.time() - t0:.0f} s", flush=True)
    xs, ys, zs = model.axes
    gi = index9.grid_index()
    positions9 = np.stack([np.asarray(a, float)[gi[:, k]] for k, a in enumerate((xs, ys, zs))], -1)
    traced = traced_all(pts)
    u = float(traced[0].sum())
    rows = [{"group": g, "r_mm": r, "position_mm": p} for g, r, p in em]
    # the true ePSFs at the emitters projected on a per-lenslet basis of the scan's node crops
    from cm2optics.lsv.decompose import lenslet_bases

    t0 = time.time()
    truth = truth_crops(model, pts)
    s0_truth = place(model, truth[0], pts[0]).sum()
    bases = lenslet_bases(crops9, 256)
    print(f"node-crop bases {[len(b) for b in bases]} {time.time() - t0:.0f} s", flush=True)
    for k in (64, 128, 256):

        def proj_k(x, k=k, bases=bases):
            out = np.zeros(x.shape)
            for j, B in enumerate(bases):
                Bk = B[:k].reshape(len(B[:k]), -1)
                out[j] = (Bk.T @ (Bk @ x[j].reshape(-1).astype(np.float32))).reshape(x.shape[1:])
            return out

        for i, (_g, _r, p) in enumerate(em):
            t = traced[i + 1] / u
            rows[i][f"crops_basis:truth_proj_K{k}"] = image_errors(place(model, proj_k(truth[i + 1] / s0_truth), p), t)
            if k == 64:
                rows[i]["crops_basis:truth"] = image_errors(place(model, truth[i + 1] / s0_truth, p), t)
        dump(rows, {"stage": "crops basis"})
        print(k, np.mean([rows[i][f"crops_basis:truth_proj_K{k}"]["error"] for i in range(len(em))]), flush=True)
    del bases, truth
    # hybrid: the model's per-lenslet basis, node coefficients projected from the scan's own crops
    from dataclasses import replace as dc_replace

    node0 = int(np.flatnonzero(np.all(np.abs(positions9) < 1e-9, axis=1))[0])
    s0_scan9 = place(model, crops9[node0].astype(np.float64), (0.0, 0.0, 0.0)).sum()
    t0 = time.time()
    coeff = np.zeros_like(model.coefficients)
    for j in range(model.n_lenslets):
        terms = model.lenslet_terms(j)
        Bj = model.basis[terms, j].reshape(len(terms), -1)
        Ginv = np.linalg.pinv(Bj.astype(np.float64) @ Bj.T.astype(np.float64))
        X = crops9[:, j].reshape(len(crops9), -1)  # (N, D) float32
        c = (Ginv @ (Bj @ X.T).astype(np.float64)) / s0_scan9  # (T, N)
        coeff[terms[:, None], gi[None, :, 2], gi[None, :, 1], gi[None, :, 0]] = c
    print(
        f"hybrid coefficients {time.time() - t0:.0f} s; model coeff scale check",
        float(np.abs(model.coefficients).max()),
        float(np.abs(coeff).max()),
        flush=True,
    )
    variants = {
        "abm_nowarp:model": dc_replace(model, warp_shapes=False, turned_coefficients=None),
        "hybrid_nowarp:model": dc_replace(model, coefficients=coeff, warp_shapes=False, turned_coefficients=None),
    }
    for name, variant in variants.items():
        t0 = time.time()
        for i, (_g, _r, p) in enumerate(em):
            rows[i][name] = image_errors(variant.point_image(*p), traced[i + 1] / u)
        print(name, f"{time.time() - t0:.0f} s", summary(rows, [name]), flush=True)
        dump(rows, {"stage": name})
    del variants
    hybrid_coefficients = coeff
    cache_pupils()
    lmodels, pmodels, record = fit_both_placements(
        design, crops9, index9, positions9, np.arange(len(positions9)), zs, model
    )
    node0 = int(np.flatnonzero(np.all(np.abs(positions9) < 1e-9, axis=1))[0])
    s0_scan9 = place(model, crops9[node0].astype(np.float64), (0.0, 0.0, 0.0)).sum()
    node_of = {tuple(np.round(q, 6)): k for k, q in enumerate(positions9)}
    J = model.n_lenslets
    offset_diff = placement_difference(lmodels, pmodels, [p for _, _, p in em])
    render, render_px = renderer(model, lmodels), renderer(model, pmodels)

    a0 = place(model, render(pts[0]), pts[0]).sum()
    project, kind = projector(model)
    t0 = time.time()
    for i, (g, _r, p) in enumerate(em):
        t = traced[i + 1] / u
        a = render(p) / s0_scan9
        rows[i]["abm:render"] = image_errors(place(model, a, p), t)
        rows[i]["abm:render_proj"] = image_errors(place(model, project(a), p), t)
        b = render_px(p) / s0_scan9
        rows[i]["abm_px:render"] = image_errors(place(model, b, p), t)
        rows[i]["abm_px:render_proj"] = image_errors(place(model, project(b), p), t)
        print("render", g, p, " ".join(f"{k} {rows[i][k]['error']:.3f}" for k in rows[i] if "render" in k), flush=True)
    print(f"renders {time.time() - t0:.0f} s", flush=True)
    dump(rows, {"stage": "renders", "pixel_vs_fine_placement": offset_diff, "s0_scan9": float(s0_scan9)})
    # node-density sweep: trilinear blend of renders at the 8 grid corners around the emitter
    sweep = [(1.0, 0.1), (0.5, 0.1), (0.25, 0.1), (0.25, 0.05)]
    picks = [i for i, (g, r, p) in enumerate(em) if (i % n) < n_sweep]
    t0 = time.time()
    for i in picks:
        g, r, p = em[i]
        t = traced[i + 1] / u
        cache = {}
        for H, Hz in sweep:
            lo = [math.floor(p[0] / H) * H, math.floor(p[1] / H) * H, math.floor(round(p[2] / Hz, 9)) * Hz]
            f = [(p[0] - lo[0]) / H, (p[1] - lo[1]) / H, (p[2] - lo[2]) / Hz]
            blend = np.zeros((J, *model.basis.shape[2:]))
            for cx in (0, 1):
                for cy in (0, 1):
                    for cz in (0, 1):
                        w = (f[0] if cx else 1 - f[0]) * (f[1] if cy else 1 - f[1]) * (f[2] if cz else 1 - f[2])
                        if w < 1e-12:
                            continue
                        q = (round(lo[0] + cx * H, 6), round(lo[1] + cy * H, 6), round(lo[2] + cz * Hz, 6))
                        if q not in cache:
                            cache[q] = render(q)
                        blend += w * cache[q]
            key = f"abm:blend_H{H:g}_z{Hz:g}"
            rows[i][key] = image_errors(place(model, blend / s0_scan9, p), t)
            if H == 1.0 and Hz == 0.1:  # the scan's own grid: its crops blended, plus the model's change
                crop_blend = np.zeros_like(blend)
                for cx in (0, 1):
                    for cy in (0, 1):
                        for cz in (0, 1):
                            w = (f[0] if cx else 1 - f[0]) * (f[1] if cy else 1 - f[1]) * (f[2] if cz else 1 - f[2])
                            q = (round(lo[0] + cx * H, 6), round(lo[1] + cy * H, 6), round(lo[2] + cz * Hz, 6))
                            if w > 1e-12:
                                crop_blend += w * crops9[node_of[tuple(np.round(q, 6))]]
                here = cache.setdefault(tuple(np.round(p, 6)), render(p))
                rows[i]["abm:crops_blend_H1"] = image_errors(place(model, crop_blend / s0_scan9, p), t)
                rows[i]["abm:crops_blend_plus_model_change_H1"] = image_errors(
                    place(model, (crop_blend + here - blend) / s0_scan9, p), t
                )
        print(
            "sweep",
            g,
            p,
            " ".join(f"{k.split(':')[1]} {rows[i][k]['error']:.3f}" for k in rows[i] if "blend" in k),
            f"{time.time() - t0:.0f} s",
            flush=True,
        )
    dump(rows, {"stage": "sweep"})
    t0 = time.time()
    variant = dc_replace(model, coefficients=hybrid_coefficients, turned_coefficients=None)
    print(f"hybrid warp recomputed {time.time() - t0:.0f} s", flush=True)
    for i, (_g, _r, p) in enumerate(em):
        rows[i]["hybrid_warp:model"] = image_errors(variant.point_image(*p), traced[i + 1] / u)
    print("hybrid_warp", summary(rows, ["hybrid_warp:model"]), flush=True)
    keys = sorted({k for r in rows for k in r if ":" in k})
    info = {
        "s0_scan9": float(s0_scan9),
        "s0_truth": float(s0_truth),
        "abm_total_at_unit_point": float(a0 / s0_scan9),
        "basis": kind,
        "sweep_emitters_per_radius": n_sweep,
        "lenslets": record,
        "pixel_vs_fine_placement": offset_diff,
    }
    json.dump({"info": info, "summary": summary(rows, keys), "rows": rows}, open(out_json, "w"), indent=1, default=str)
    for g, v in summary(rows, keys).items():
        print(g, v["n"], " ".join(f"{k} {v[k]['error']:.3f}" for k in keys if k in v))


def main_abmfit(n, out_json, model_path, scan9):
    """Goal 3, trimmed for time: the aberration model's placement fitted to the fine crops and to the
    whole-pixel windows (each at its phase), both on the nodes of every second depth (session 10's
    rule), its renders at the emitters at full rank and on the model's basis."""
    from cm2optics.design import load_preset
    from cm2optics.formats.scan import open_scan
    from cm2optics.lsv.epsf import epsf_crops
    from cm2optics.lsv.model import load_model

    design = load_preset("cm2-v2")
    em = positions(n)
    pts = [(0.0, 0.0, 0.0)] + [p for _, _, p in em]
    model = load_model(model_path)
    S = model.oversample
    index9 = open_scan(scan9)
    xs, ys, zs = model.axes
    gi = index9.grid_index()
    positions9 = np.stack([np.asarray(a, float)[gi[:, k]] for k, a in enumerate((xs, ys, zs))], -1)
    fit_nodes = np.flatnonzero(gi[:, 2] % 2 == 0)
    t0 = time.time()
    crops9 = np.asarray(epsf_crops(index9, model.geometry, model.patch_shape, S))
    node0 = int(np.flatnonzero(np.all(np.abs(positions9) < 1e-9, axis=1))[0])
    s0_scan9 = place(model, crops9[node0].astype(np.float64), (0.0, 0.0, 0.0)).sum()
    print(f"crops {time.time() - t0:.0f} s", flush=True)
    cache_pupils()
    lmodels, pmodels, _ = fit_both_placements(design, crops9, index9, positions9, fit_nodes, zs, model)
    del crops9
    offset_diff = placement_difference(lmodels, pmodels, [p for _, _, p in em])
    renders = {"abm": renderer(model, lmodels), "abm_px": renderer(model, pmodels)}

    traced = traced_all(pts)
    u = float(traced[0].sum())
    rows = [{"group": g, "r_mm": r, "position_mm": p} for g, r, p in em]
    t0 = time.time()
    for i, (g, r, p) in enumerate(em):
        t = traced[i + 1] / u
        for name, render in renders.items():
            a = render(p) / s0_scan9
            rows[i][f"{name}:render"] = image_errors(place(model, a, p), t)
            rows[i][f"{name}:render_on_basis"] = image_errors(place(model, model.project(a), p), t)
        print("render", g, p, " ".join(f"{k} {rows[i][k]['error']:.3f}" for k in rows[i] if ":" in k), flush=True)
        if i % 8 == 7:
            keys = sorted({k for r in rows for k in r if ":" in k})
            json.dump(
                {
                    "info": {"pixel_vs_fine_placement": offset_diff, "fit_nodes": len(fit_nodes)},
                    "summary": summary(rows[: i + 1], keys),
                    "rows": rows[: i + 1],
                },
                open(out_json, "w"),
                indent=1,
            )
    keys = sorted({k for r in rows for k in r if ":" in k})
    json.dump(
        {
            "info": {"pixel_vs_fine_placement": offset_diff, "fit_nodes": len(fit_nodes)},
            "summary": summary(rows, keys),
            "rows": rows,
        },
        open(out_json, "w"),
        indent=1,
    )
    for g, v in summary(rows, keys).items():
        print(g, v["n"], " ".join(f"{k} {v[k]['error']:.3f}" for k in keys if k in v))


if __name__ == "__main__":
    step = sys.argv[1]
    if step == "positions":
        n, out = int(sys.argv[2]), sys.argv[3]
        em = positions(n)
        with open(out, "w") as fh:
            fh.write("x_mm,y_mm,z_mm\n0,0,0\n")
            for _, _, p in em:
                fh.write(f"{p[0]:.6f},{p[1]:.6f},{p[2]:.6f}\n")
        print(len(em) + 1, "positions")
    elif step == "truth":
        main_truth(int(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5:])
    elif step == "abm":
        main_abm(
            int(sys.argv[2]),
            sys.argv[3],
            sys.argv[4],
            sys.argv[5],
            sys.argv[6],
            int(sys.argv[7]) if len(sys.argv) > 7 else 4,
        )
    elif step == "abmfit":
        main_abmfit(int(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5])
