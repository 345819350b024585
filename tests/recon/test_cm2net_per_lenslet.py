"""CM²Net's training data through a per-lenslet 3D-LSV model (``cm2 lsv build --per-lenslet-basis``):
the shared tiny model rewritten as the per-lenslet model it equals (lenslet j's terms = the shared
basis's focus patches in lenslet j only, their coefficients repeated per lenslet) gives the same
registered views, demixed views and targets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from tiny_net import tiny

from cm2optics.recon.net.data import Item, PatchSource
from cm2optics.synth.config import SynthConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_a_per_lenslet_model_makes_the_same_patches_as_the_shared_basis_it_equals(lsv_model, lsv_model_path, tmp_path):
    K, J = lsv_model.basis.shape[:2]
    basis = np.zeros((J * K,) + lsv_model.basis.shape[1:], lsv_model.basis.dtype)
    for j in range(J):
        basis[j * K : (j + 1) * K, j] = lsv_model.basis[:, j]
    per_lenslet = replace(
        lsv_model,
        basis=basis,
        coefficients=np.tile(lsv_model.coefficients, (J, 1, 1, 1)),
        singular_values=np.tile(np.asarray(lsv_model.singular_values), J),
    )
    assert [list(per_lenslet.lenslet_terms(j)) for j in range(J)] == [list(range(j * K, (j + 1) * K)) for j in range(J)]
    path = per_lenslet.save(tmp_path / "per-lenslet.lsv.h5")
    voxel = lsv_model.default_grid.voxel_um[1]
    synth = SynthConfig.scaled(
        4, voxel_um=(50.0, voxel, voxel), depth_um=300.0, view_px=64, patch_px=32, patches_per_volume=2
    )
    config = tiny(forward_model=str(lsv_model_path), synth=synth, n_planes=synth.grid.shape[0], register_views=True)
    shared, own = PatchSource(config), PatchSource(config.with_changes(forward_model=str(path)))
    for k in range(2):
        item = Item(5, 0, k, (40.0, 60.0))
        a, b = shared.patch(item), own.patch(item)
        assert a["views"].max() > 0
        for key in ("views", "demixed", "volume"):
            np.testing.assert_allclose(b[key], a[key], rtol=1e-4, atol=1e-6 * float(np.abs(a[key]).max()), err_msg=key)
