"""The MLA part against closed forms: sag, pitch, thickness, volume, mesh fidelity."""

from __future__ import annotations

import math

import cadquery as cq
import numpy as np
import pytest
import trimesh

from cm2optics.cad.mla import build_mla, lens_cells, lens_rms_deviation_um, mla_volume_mm3
from cm2optics.cad.tessellate import DEFAULT_TOLERANCE_UM, export_stl
from cm2optics.design import SystemDesign


@pytest.fixture(scope="module")
def mla_solid(v2: SystemDesign) -> cq.Solid:
    return build_mla(v2).val()


def _mesh(shape: cq.Shape, tmp_path, tolerance_um: float = DEFAULT_TOLERANCE_UM) -> trimesh.Trimesh:
    path = tmp_path / "mla.stl"
    export_stl(shape, path, tolerance_um / 1000)
    return trimesh.load(path, force="mesh")


def test_single_valid_solid_with_design_envelope(v2, mla_solid):
    bb = mla_solid.BoundingBox()
    assert mla_solid.isValid()
    assert (bb.xlen, bb.ylen, bb.zmin, bb.zmax) == pytest.approx((3.0, 3.0, 0.0, v2.mla.thickness_mm), abs=1e-6)


def test_sag_closed_form(v2):
    r = v2.mla.radius_mm
    # 100 % fill factor: the crease at a cell corner sits r − √(r² − 0.5 p²) below the vertex.
    assert v2.mla.corner_sag_mm == pytest.approx(r - math.sqrt(r**2 - 0.5), rel=1e-12)
    assert v2.mla.sag_mm(0.5) == pytest.approx(0.0776, abs=1e-4)


def test_brep_volume_matches_quadrature(v2, mla_solid):
    assert mla_solid.Volume() == pytest.approx(mla_volume_mm3(v2.mla), rel=1e-6)


def test_lenslet_vertices_on_the_pitch(v2, tmp_path, mla_solid):
    mesh = _mesh(mla_solid, tmp_path)
    top = mesh.vertices[mesh.vertices[:, 2] > v2.mla.thickness_mm - 1e-4]
    for x, y in v2.mla.lenslet_centres_mm():
        near = np.linalg.norm(top[:, :2] - [x, y], axis=1).min()
        assert near < 0.03, (x, y, near)
    centres = np.array(v2.mla.lenslet_centres_mm())
    assert np.allclose(np.unique(np.round(centres[:, 0], 9)), [-1.0, 0.0, 1.0])


def test_mesh_watertight_true_volume_and_lens_fidelity(v2, tmp_path, mla_solid):
    mesh = _mesh(mla_solid, tmp_path)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(mla_solid.Volume(), rel=0.005)
    fine = lens_rms_deviation_um(v2, mesh)
    assert fine["lens_rms_deviation_um"] <= 1.0
    # The deviation follows the tolerance (chord error ∝ tolerance): the check can fail.
    coarse = lens_rms_deviation_um(v2, _mesh(build_mla(v2).val(), tmp_path, tolerance_um=4.0))
    assert coarse["lens_rms_deviation_um"] > 2.5 * fine["lens_rms_deviation_um"]


def test_partial_lenslets_add_diced_columns(v2, tmp_path):
    design = v2.with_changes({"mla.partial_border_mm": 0.4, "mla.partial_sides": ["+x", "-y"]})
    cells = lens_cells(design.mla)
    assert sum(c.partial for c in cells) == 3 + 3 + 1
    solid = build_mla(design).val()
    bb = solid.BoundingBox()
    assert (bb.xmin, bb.xmax, bb.ymin, bb.ymax) == pytest.approx((-1.5, 1.9, -1.9, 1.5), abs=1e-6)
    assert solid.Volume() == pytest.approx(mla_volume_mm3(design.mla), rel=1e-6)
    assert _mesh(solid, tmp_path).is_watertight


def test_square_lenses_on_a_land(v2):
    design = v2.with_changes({"mla.aperture_mm": 0.8})
    solid = build_mla(design).val()
    assert solid.isValid() and len(solid.Solids()) == 1
    assert solid.Volume() == pytest.approx(mla_volume_mm3(design.mla), rel=1e-5)
