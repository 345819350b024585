"""`cm2 cad export` end to end: every part watertight and true to its solid, printable,
fitted, the assembly free of clashes, pictures written, and `cad/` in step with the code."""

from __future__ import annotations

import json
from pathlib import Path

import cadquery as cq
import numpy as np
import pytest
import trimesh
from PIL import Image

from cm2optics.cad import assembly
from cm2optics.cad.export import export_design
from cm2optics.design import load_preset

COMMITTED = Path(__file__).resolve().parents[2] / "cad"


@pytest.fixture(scope="module")
def exported(tmp_path_factory, v2):
    out = tmp_path_factory.mktemp("export") / "cad"
    manifest = export_design(v2, out, wall_samples=5000, show_progress=False)
    return out, manifest


def test_manifest_schema(exported):
    out, manifest = exported
    assert json.loads((out / "manifest.json").read_text()) == manifest
    for part in manifest["parts"]:
        assert {"name", "file", "volume_mm3", "bbox_mm", "watertight", "min_wall_mm"} <= set(part)
        assert (out / part["file"]).is_file() and (out / f"{part['name']}.step").is_file()
    assert isinstance(manifest["assembly"]["interferences"], list)
    names = {p["name"] for p in manifest["parts"]}
    assert {
        "mla",
        "collimator",
        "mla_housing",
        "led_housing",
        "base_plate",
        "emission_filter",
        "absorption_filter",
        "excitation_filter",
        "aperture_mask",
    } <= names
    assert (out / "assembly.stl").is_file() and (out / "assembly.step").is_file()


def test_every_mesh_is_watertight_and_true_to_its_solid(exported):
    out, manifest = exported
    for part in manifest["parts"]:
        mesh = trimesh.load(out / part["file"], force="mesh")
        assert mesh.is_watertight and mesh.is_winding_consistent, part["name"]
        assert mesh.volume == pytest.approx(part["volume_mm3"], rel=0.005), part["name"]
        assert part["watertight"] and part["volume_error"] <= 0.005


def test_lens_surfaces_within_a_micrometre(exported):
    mla = next(p for p in exported[1]["parts"] if p["name"] == "mla")
    assert mla["lens_rms_deviation_um"] <= 1.0


def test_printed_parts_walls_fits_and_no_interference(exported, v2):
    manifest = exported[1]
    printed = [p for p in manifest["parts"] if p["printed"]]
    assert {p["name"] for p in printed} == {"mla_housing", "led_housing", "base_plate", "collimator"}
    for part in printed:
        assert part["min_wall_mm"] >= v2.mechanics.min_wall_mm, part["name"]
    fits = manifest["assembly"]["fits"]
    assert len(fits) >= 8
    assert all(0.05 <= f["clearance_mm"] <= 0.2 for f in fits), fits
    assert manifest["assembly"]["interferences"] == []
    assert all(manifest["checks"].values()), manifest["checks"]
    counts = {p["name"]: p["count"] for p in manifest["parts"]}
    assert counts["led_housing"] == counts["collimator"] == 4


def test_pictures_show_something(exported):
    out, manifest = exported
    for name in ["assembly.png", "assembly_section.png"] + [p["png"] for p in manifest["parts"]]:
        pixels = np.asarray(Image.open(out / name).convert("L"), dtype=float)
        assert pixels.std() > 5, name


def test_interference_check_can_fail(v2):
    housing = assembly.PlacedPart("housing", "mla_housing", cq.Workplane().box(10, 10, 10).val(), np.eye(4))
    inside = assembly.PlacedPart("intruder", "mla", cq.Workplane().box(2, 2, 2).translate((4.5, 0, 0)).val(), np.eye(4))
    apart = assembly.PlacedPart("apart", "mla", cq.Workplane().box(2, 2, 2).translate((20, 0, 0)).val(), np.eye(4))
    clashes = assembly.interferences([housing, inside, apart])
    assert [(c["a"], c["b"]) for c in clashes] == [("housing", "intruder")]
    assert clashes[0]["volume_mm3"] == pytest.approx(1.5 * 2 * 2, rel=1e-6)


def test_v1_exports_without_film_and_collimator(tmp_path, v1):
    manifest = export_design(v1, tmp_path / "v1", formats="stl", pictures=False, wall_samples=2000, show_progress=False)
    names = {p["name"] for p in manifest["parts"]}
    assert "collimator" not in names and "absorption_filter" not in names
    assert manifest["assembly"]["interferences"] == []
    assert all(manifest["checks"].values())
    assert not list(tmp_path.glob("*.step")) and not list((tmp_path / "v1").glob("*.step"))


def test_failed_export_leaves_nothing_behind(tmp_path, v2, monkeypatch):
    def broken(design):
        raise RuntimeError("boom")

    specs = assembly.part_specs(v2)
    specs[-1] = assembly.PartSpec(specs[-1].name, broken, True, "x", "fails on purpose")
    monkeypatch.setattr("cm2optics.cad.export.part_specs", lambda design: specs)
    with pytest.raises(RuntimeError, match="boom"):
        export_design(v2, tmp_path / "cad", pictures=False, show_progress=False)
    assert list(tmp_path.iterdir()) == []


def test_committed_cad_matches_the_code(exported, v2):
    """`cad/` holds the default design's parts, as STL and STEP (each STEP solid of its part's
    volume): regenerate with `cm2 cad export --preset cm2-v2 --out cad/`."""
    committed = json.loads((COMMITTED / "manifest.json").read_text())
    fresh = exported[1]
    assert committed["parameter_hash"] == v2.parameter_hash() == fresh["parameter_hash"]
    assert load_preset(str(COMMITTED / "design.yaml")) == v2
    assert (COMMITTED / "assembly.step").is_file()
    for part in committed["parts"]:
        step = cq.importers.importStep(str(COMMITTED / f"{part['name']}.step")).val()
        assert step.Volume() == pytest.approx(part["volume_mm3"], rel=1e-6), part["name"]
    assert [p["name"] for p in committed["parts"]] == [p["name"] for p in fresh["parts"]]
    for old, new in zip(committed["parts"], fresh["parts"], strict=True):
        assert old["volume_mm3"] == pytest.approx(new["volume_mm3"], rel=1e-4), old["name"]
        np.testing.assert_allclose(old["bbox_mm"], new["bbox_mm"], atol=2e-3, err_msg=old["name"])
        mesh = trimesh.load(COMMITTED / old["file"], force="mesh")
        assert mesh.is_watertight and mesh.volume == pytest.approx(new["volume_mm3"], rel=0.005), old["name"]
    assert committed["assembly"]["interferences"] == fresh["assembly"]["interferences"]


def test_design_yaml_written_with_the_parts(exported, v2):
    out, _ = exported
    assert load_preset(str(out / "design.yaml")) == v2
