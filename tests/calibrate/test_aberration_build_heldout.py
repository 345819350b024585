"""`aberration_psfs(held_out=…)`, the refit behind `cm2 lsv validate --refit`: the held-out nodes
enter neither the traced pupils nor the placement fit, and the PSFs returned are the model's at
the held-out positions (tracer and fits replaced by recorders: the plumbing, in milliseconds)."""

from __future__ import annotations

import itertools

import numpy as np

import cm2optics.calibrate.aberration_build as build
import cm2optics.emission.psf as psf
from cm2optics.lsv.preprocess import Geometry


class _Model:
    def __init__(self, lenslet, seen):
        self.lenslet, self.seen = lenslet, seen

    def predict(self, position):
        return np.full((4, 4), 100 * self.lenslet + float(np.sum(np.abs(position))))


def _grid_without_optics(monkeypatch, J):
    """A 9 × 9 × 2 node grid over ±4 mm, lenslet axes and the emission model stubbed out."""
    monkeypatch.setattr(build, "lenslet_axes", lambda geometry, z: np.zeros((J, 2)))
    monkeypatch.setattr(psf, "EmissionModel", lambda *a: None)
    xs = ys = np.linspace(-4, 4, 9)
    zs = np.array([-0.1, 0.1])
    gi = np.array([[ix, iy, iz] for iz in range(2) for iy in range(9) for ix in range(9)])
    positions = np.stack([xs[gi[:, 0]], ys[gi[:, 1]], zs[gi[:, 2]]], -1)
    return xs, ys, zs, gi, positions


def test_held_out_nodes_enter_neither_the_pupils_nor_the_placement(monkeypatch):
    seen = {"traced": None, "placed": {}}
    J = 2

    def trace(emission, positions, seed=0, progress=None):
        seen["traced"] = np.asarray(positions)
        return {j: [object()] * len(positions) for j in range(J)}

    def placement(model, crops, positions, samplers=None):
        seen["placed"][model.lenslet] = np.asarray(positions)
        return model

    counter = itertools.cycle(range(J))
    monkeypatch.setattr(build, "trace_pupils", trace)
    monkeypatch.setattr(build, "fit_lenslet_model", lambda *a, **k: _Model(next(counter), seen))
    monkeypatch.setattr(build, "fit_placement", placement)
    xs, ys, zs, gi, positions = _grid_without_optics(monkeypatch, J)
    crops = np.ones((len(gi), J, 4, 4), np.float32)
    held = np.array([30, 40, 121])
    geometry = Geometry.__new__(Geometry)
    nodes, dense, record = build.aberration_psfs(
        None, crops, gi, (xs, ys, zs), geometry, 4, 4.0, dense=5, held_out=held, memory_bytes=1 << 30
    )
    assert len(seen["traced"]) == len(gi) - 3
    assert not any(np.all(seen["traced"] == positions[n], axis=1).any() for n in held)
    for j in range(J):
        placed = seen["placed"][j]
        assert len(placed) > 0 and not any(np.all(placed == positions[n], axis=1).any() for n in held)
        assert np.all(np.abs(placed[:, :2]) <= 3 + 1e-9)  # the placement's field share (0.75 of ±4 mm)
    assert nodes.shape == (3, J, 4, 4) and dense.shape == (5, J, 4, 4)
    for i, n in enumerate(held):  # the model's PSFs at the held-out positions, in their order
        np.testing.assert_allclose(nodes[i, 1], 100 + np.abs(positions[n]).sum())
    assert record["held_out_nodes"] == 3 and record["dense_positions"] == 5
    full, _, _ = build.aberration_psfs(None, crops, gi, (xs, ys, zs), geometry, 4, 4.0, dense=5, memory_bytes=1 << 30)
    assert full.shape == (len(gi), J, 4, 4) and len(seen["traced"]) == len(gi)  # without held_out: every node


def test_whole_pixel_windows_place_the_model_at_each_frames_own_phase(monkeypatch):
    """A scan without fine ePSFs: the placement gets each node's whole-pixel window with a sampler
    at that node's and lenslet's phase, and the PSFs are rendered ``oversample`` times finer."""
    J, S, h = 2, 4, 8
    seen = {"shape": None, "placed": {}}

    class _Fine:
        def __init__(self, lenslet):
            self.lenslet = lenslet

        def predict(self, position):
            return np.full(seen["shape"], float(self.lenslet))

    def placement(model, crops, positions, samplers=None):
        seen["placed"][model.lenslet] = (np.asarray(positions), samplers, crops)
        return model

    counter = itertools.cycle(range(J))

    def fit_model(own, axis, shape, sample_mm, oversample):
        seen["shape"] = shape
        return _Fine(next(counter))

    monkeypatch.setattr(build, "trace_pupils", lambda e, p, seed=0, progress=None: {j: [0] * len(p) for j in range(J)})
    monkeypatch.setattr(build, "fit_lenslet_model", fit_model)
    monkeypatch.setattr(build, "fit_placement", placement)
    xs, ys, zs, gi, positions = _grid_without_optics(monkeypatch, J)
    windows = np.ones((len(gi), J, h, h), np.float32)
    phases = np.random.default_rng(1).uniform(0, 1, (len(gi), J, 2))
    geometry = Geometry.__new__(Geometry)
    nodes, dense, record = build.aberration_psfs(
        None, windows, gi, (xs, ys, zs), geometry, S, 4.8, dense=3, memory_bytes=1 << 30, phases=phases
    )
    assert seen["shape"] == (h * S, h * S) and nodes.shape == (len(gi), J, h * S, h * S)
    assert dense.shape == (3, J, h * S, h * S) and record["placement_from"].startswith("whole-pixel")
    ramp = np.broadcast_to(np.arange(h * S, dtype=float)[:, None], (h * S, h * S))  # fine row coordinate
    for j in range(J):
        placed, samplers, crops = seen["placed"][j]
        assert len(samplers) == len(crops) == len(placed) > 0
        for sample, position in zip(samplers[:5], placed[:5], strict=True):
            n = int(np.flatnonzero(np.all(positions == position, axis=1))[0])
            rows = sample(ramp)[2:-2, 2:-2]  # interior: the Keys kernel reproduces a ramp exactly
            expected = (np.arange(2, h - 2) - phases[n, j, 0]) * S
            np.testing.assert_allclose(rows, np.broadcast_to(expected[:, None], rows.shape), atol=1e-9)
