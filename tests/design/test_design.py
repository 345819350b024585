"""SystemDesign: presets, derived optics against closed forms, YAML validation errors."""

from __future__ import annotations

import dataclasses

import pytest
import yaml

from cm2optics.design import (
    DesignError,
    MicrolensArray,
    Side,
    SystemDesign,
    available_presets,
    design_from_dict,
    load_design,
    load_preset,
)
from cm2optics.design.materials import Material, refractive_index
from cm2optics.optics import first_order
from cm2optics.optics.first_order import chief_ray_magnification
from cm2optics.optics.focus import on_axis_wavefront_rms_waves


def test_presets_ship_and_load():
    assert {"cm2-v1", "cm2-v2"} <= set(available_presets())
    v1, v2 = load_preset("cm2-v1"), load_preset("cm2-v2")
    assert (v2.sensor.width_px, v2.sensor.height_px, v2.sensor.pixel_um, v2.sensor.bit_depth) == (3088, 2076, 2.4, 12)
    assert (v1.sensor.width_px, v1.sensor.height_px, v1.sensor.pixel_um) == (2592, 1944, 2.2)
    assert v1.collimator is None and v1.absorption_filter is None
    assert v2.collimator is not None and v2.absorption_filter is not None


def test_v2_matches_the_paper(v2: SystemDesign):
    mla = v2.mla
    assert (mla.rows, mla.cols, mla.pitch_mm, mla.radius_mm, mla.thickness_mm, mla.material) == (
        3,
        3,
        1.0,
        1.65,
        3.3,
        Material.PMMA,
    )
    assert first_order.magnification(v2) == pytest.approx(0.57, rel=0.03)
    assert first_order.object_pixel_um(v2) == pytest.approx(4.15, rel=0.02)
    assert first_order.working_distance_mm(v2) == pytest.approx(10.0, abs=1.0)
    assert first_order.object_na(v2) == pytest.approx(0.05, abs=0.005)
    assert v2.led_array.count == 4  # placed by the uniform-illumination design (issue 16), not the paper
    assert (v2.emission_filter.width_mm, v2.emission_filter.length_mm, v2.emission_filter.thickness_mm) == (
        6.0,
        6.0,
        1.0,
    )
    assert v2.absorption_filter.thickness_mm == 0.1
    assert (v2.volume.field_mm, v2.volume.depth_mm) == (8.0, 0.8)


def _thick_lens(design: SystemDesign) -> tuple[float, float, float]:
    """Image distance s_i from the rear principal plane, the reduced object-side offset of the
    filter plate, and the focal length, from the thick plano-convex lens formulas (independently)."""
    lam = design.imaging.design_wavelength_nm
    n = refractive_index(design.mla.material, lam)
    f = design.mla.radius_mm / (n - 1)
    film = design.absorption_filter
    back = design.imaging.mla_to_sensor_mm
    if film is not None:
        back -= film.thickness_mm * (1 - 1 / refractive_index(film.material, lam))
    s_i = back + design.mla.thickness_mm / n  # from the rear principal plane (t/n inside the flat face)
    filt = design.emission_filter
    plate = filt.thickness_mm * (1 - 1 / refractive_index(filt.material, lam))
    return s_i, plate, f


@pytest.mark.parametrize("preset", ["cm2-v1", "cm2-v2"])
def test_paraxial_conjugates_match_thick_lens_formulas(preset):
    design = load_preset(preset)
    s_i, plate, f = _thick_lens(design)
    s_o = 1 / (1 / f - 1 / s_i)  # from the front principal plane, at the vertex
    assert first_order.paraxial_object_plane_z_mm(design) == pytest.approx(
        design.mla_vertex_z_mm + s_o + plate, rel=1e-9
    )
    assert first_order.paraxial_magnification(design) == pytest.approx(s_i / s_o, rel=1e-9)


@pytest.mark.parametrize("preset", ["cm2-v1", "cm2-v2"])
def test_chief_ray_magnification_matches_the_thick_lens(preset):
    # The stop (the lenslet's vertex) is the front principal plane, so the exit pupil is the
    # rear one: a source plane at reduced distance s_o images its chief rays with |m| = s_i / s_o.
    design = load_preset(preset)
    s_i, plate, _ = _thick_lens(design)
    for height in (
        first_order.object_plane_z_mm(design),
        first_order.paraxial_object_plane_z_mm(design),
        first_order.object_plane_z_mm(design) + 0.5,
    ):
        s_o = height - design.mla_vertex_z_mm - plate
        assert chief_ray_magnification(design, height) == pytest.approx(s_i / s_o, rel=1e-9)
    assert first_order.magnification(design) == pytest.approx(
        s_i / (first_order.working_distance_mm(design) - plate), rel=1e-9
    )
    assert chief_ray_magnification(design, first_order.paraxial_object_plane_z_mm(design)) == pytest.approx(
        first_order.paraxial_magnification(design), rel=1e-9
    )


@pytest.mark.parametrize("preset", ["cm2-v1", "cm2-v2"])
def test_focal_plane_is_the_best_focus(preset):
    # Under-corrected spherical aberration (≈ 1 wave RMS at the paraxial image of a 1-mm
    # plano-convex lenslet at NA' ≈ 0.1): the least RMS wavefront error lies ≈ 0.8 mm nearer the
    # device, where it is about a third of the paraxial plane's.
    design = load_preset(preset)
    best = first_order.object_plane_z_mm(design)
    assert 0.6 < first_order.focus_shift_mm(design) < 1.0
    rms = {dz: on_axis_wavefront_rms_waves(design, best + dz) for dz in (-0.05, 0.0, 0.05)}
    assert rms[0.0] < rms[-0.05] and rms[0.0] < rms[0.05]
    paraxial = on_axis_wavefront_rms_waves(design, first_order.paraxial_object_plane_z_mm(design))
    assert 0.8 < paraxial < 1.3 and rms[0.0] < paraxial / 2.5
    assert first_order.object_z_to_height_mm(design, 0.0) == best


def test_authors_zemax_spacing_puts_the_focal_plane_where_their_file_does(v2: SystemDesign):
    # Their Zemax file: MLA flat face 2.94 mm from the sensor, object plane ≈ 16.2 mm, m ≈ 0.53–0.57
    # (paraxial); the preset uses their spacing, whose best focus has the paper's object pixel.
    assert v2.imaging.mla_to_sensor_mm == 2.94
    assert first_order.paraxial_object_plane_z_mm(v2) == pytest.approx(16.2, abs=0.1)
    assert 0.52 <= first_order.paraxial_magnification(v2) <= 0.57
    assert first_order.object_pixel_um(v2) == pytest.approx(4.15, rel=0.01)


def test_yaml_round_trip_and_hash(v2: SystemDesign, tmp_path):
    path = tmp_path / "d.yaml"
    v2.save(path)
    again = load_design(path)
    assert again == v2 and again.parameter_hash() == v2.parameter_hash()
    changed = v2.with_changes({"mla.radius_mm": 1.7})
    assert changed.mla.radius_mm == 1.7 and changed.parameter_hash() != v2.parameter_hash()


def test_default_aim_stays_out_of_the_yaml_and_a_new_aim_round_trips(v2: SystemDesign, v2_collimating, tmp_path):
    centred = v2_collimating
    assert centred.led_array.aim_mm == 0.0 and "aim_mm" not in centred.to_dict()["led_array"]
    assert v2.to_dict()["led_array"]["aim_mm"] == 1.5  # the shipped design aims short of the centre
    aimed = centred.with_changes({"led_array.aim_mm": -1.5})
    assert aimed.to_dict()["led_array"]["aim_mm"] == -1.5 and aimed.parameter_hash() != centred.parameter_hash()
    aimed.save(tmp_path / "aimed.yaml")
    assert load_design(tmp_path / "aimed.yaml") == aimed
    with pytest.raises(DesignError, match="untilted"):
        v2.with_changes({"led_array.tilt_deg": 0.0, "led_array.aim_mm": 1.0})


def _data(v2: SystemDesign) -> dict:
    return yaml.safe_load(v2.to_yaml())


def test_missing_field_names_it(v2):
    data = _data(v2)
    del data["mla"]["radius_mm"]
    with pytest.raises(DesignError, match=r"^mla\.radius_mm = None: missing"):
        design_from_dict(data)


def test_misspelled_field_suggests_the_right_one(v2):
    data = _data(v2)
    data["mla"]["raduis_mm"] = data["mla"].pop("radius_mm")
    with pytest.raises(DesignError, match=r"mla\.raduis_mm.*did you mean 'radius_mm'"):
        design_from_dict(data)


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("mla.pitch_mm", "one", "must be a number"),
        ("mla.rows", 3.0, "must be an integer"),
        ("mla.material", "glass", "must be one of"),
        ("mla.partial_sides", "+x", "must be a list"),
        ("emission_filter.thickness_mm", -1.0, "must be a finite number > 0"),
        ("mla.aperture_mm", 1.2, "cannot be larger than its cell"),
        ("collimator.footprint_mm", 8.0, "wider than its housing"),
        ("sensor.bit_depth", 11, "one of 8, 10, 12"),
        ("mechanics.clearance_mm", 0.5, "0.05–0.2"),
        ("imaging.film_to_sensor_mm", 3.2, "must lie below the MLA"),
        ("led_array.aim_mm", 8.2, "within ±offset_mm"),  # offset_mm = 7.5
        ("led_array.aim_mm", -8.5, "within ±offset_mm"),
    ],
)
def test_bad_values_name_field_value_and_range(v2, path, value, message):
    data = _data(v2)
    section, leaf = path.split(".")
    data[section][leaf] = value
    with pytest.raises(DesignError) as info:
        design_from_dict(data)
    assert info.value.field == path
    assert message in str(info.value)
    assert repr(value) in str(info.value) or str(value) in str(info.value)


def test_direct_construction_validates_too(v2):
    with pytest.raises(DesignError, match="radius_mm"):
        dataclasses.replace(v2.mla, radius_mm=-1.0)
    ok = dataclasses.replace(v2.mla, partial_border_mm=0.4, partial_sides=(Side.PLUS_X,))
    assert isinstance(ok, MicrolensArray) and ok.width_mm == pytest.approx(3.4)


def test_unknown_preset_and_bad_files(tmp_path):
    with pytest.raises(DesignError, match="unknown preset"):
        load_preset("cm9")
    with pytest.raises(DesignError, match="no such file"):
        load_design(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("mla: [unclosed\n")
    with pytest.raises(DesignError, match="not valid YAML"):
        load_design(bad)
    bad.write_text("- a list\n")
    with pytest.raises(DesignError, match="mapping"):
        load_design(bad)


def test_with_changes_rejects_unknown_paths(v2):
    with pytest.raises(DesignError, match="no such field"):
        v2.with_changes({"mla.nope": 1})
