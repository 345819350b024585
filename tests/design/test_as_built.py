"""The as-built section of a design: optional, default-valued fields leave the design (and its
hash) as it was; validated values; YAML round trip; dotted changes."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import pytest
import yaml

from cm2optics.design import AsBuilt, DesignError, SystemDesign, design_from_dict, load_design
from cm2optics.design.coerce import to_plain


def _hash_without_as_built(design: SystemDesign) -> str:
    """The parameter hash as it was before the section (and ``illumination_as_built``, ``led_array.aim_mm``,
    ``collimator.lens_freeform_um``, the TIR wall's ``tir_max_radius_mm``, cone and azimuthal terms) existed: every part but as_built, the aim only where it is
    not the field's centre, the lens's Zernike terms only where one is not zero."""
    data = to_plain(design)
    del data["as_built"], data["illumination_as_built"]
    if data["led_array"]["aim_mm"] == 0.0:
        del data["led_array"]["aim_mm"]
    if data["collimator"] is not None and not any(data["collimator"]["lens_freeform_um"]):
        del data["collimator"]["lens_freeform_um"]
    for wall in ("tir_max_radius_mm", "tir_cone_deg", "tir_cone_curvature_per_mm", "tir_cos2", "tir_cos4"):
        if data["collimator"] is not None and data["collimator"][wall] == 0.0:
            del data["collimator"][wall]
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def test_absent_or_default_section_leaves_the_design_unchanged(v2: SystemDesign):
    assert v2.as_built == AsBuilt()
    assert "as_built" not in v2.to_dict()
    assert v2.parameter_hash() == _hash_without_as_built(v2)
    explicit = dataclasses.replace(
        v2, as_built=AsBuilt(lenslet_transmission=(1.0,) * 9, lenslet_decenter_mm=((0.0, 0.0),) * 9)
    )
    assert explicit.parameter_hash() == v2.parameter_hash()
    data = v2.to_dict()
    data["as_built"] = {"mla_rotation_deg": 0.0, "stray_light_width_um": 200}
    assert design_from_dict(data).parameter_hash() == v2.parameter_hash()


def test_non_default_values_change_the_hash_and_round_trip(v2: SystemDesign, tmp_path):
    built = v2.with_changes(
        {
            "as_built.mla_rotation_deg": 0.5,
            "as_built.mla_decenter_x_mm": -0.03,
            "as_built.lenslet_transmission": [1, 1, 1, 1, 0.6, 1, 1, 1, 1],
            "as_built.lenslet_decenter_mm": [[0, 0]] * 8 + [[0.01, -0.02]],
            "as_built.stray_light_fraction": 0.1,
        }
    )
    assert built.as_built.mla_rotation_deg == 0.5 and built.as_built.transmission(4) == 0.6
    assert built.as_built.lenslet_offset_mm(8) == (0.01, -0.02)
    assert built.parameter_hash() != v2.parameter_hash()
    section = built.to_dict()["as_built"]
    assert set(section) == {
        "mla_rotation_deg",
        "mla_decenter_x_mm",
        "lenslet_transmission",
        "lenslet_decenter_mm",
        "stray_light_fraction",
    }
    path = tmp_path / "built.yaml"
    built.save(path)
    again = load_design(path)
    assert again == built and again.parameter_hash() == built.parameter_hash()
    assert yaml.safe_load(path.read_text())["as_built"]["mla_rotation_deg"] == 0.5
    assert built.as_built.image_effects() == {"stray_light": {"fraction": 0.1, "width_um": 200.0}}


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"as_built.mla_rotation_deg": 4.0}, "as_built.mla_rotation_deg"),
        ({"as_built.mla_decenter_y_mm": 0.3}, "as_built.mla_decenter_y_mm"),
        ({"as_built.lenslet_pitch_delta_mm": float("nan")}, "as_built.lenslet_pitch_delta_mm"),
        ({"as_built.stray_light_fraction": 0.7}, "as_built.stray_light_fraction"),
        ({"as_built.sensor_tilt_x_deg": "two"}, "as_built.sensor_tilt_x_deg"),
        ({"as_built.lenslet_transmission": [1.0] * 8}, "as_built.lenslet_transmission"),
        ({"as_built.lenslet_transmission": [1.0] * 8 + [-0.1]}, "as_built.lenslet_transmission[8]"),
        ({"as_built.lenslet_decenter_mm": [[0.0, 0.0]] * 8 + [[0.2, 0.0]]}, "as_built.lenslet_decenter_mm[8]"),
        ({"as_built.lenslet_decenter_mm": [[0.0]] * 9}, "as_built.lenslet_decenter_mm[0]"),
        ({"as_built.mla_spin_deg": 1.0}, "as_built.mla_spin_deg"),
    ],
)
def test_bad_values_name_the_field(v2: SystemDesign, changes, field):
    with pytest.raises(DesignError) as error:
        v2.with_changes(changes)
    assert error.value.field == field


def test_unknown_key_in_yaml_section_is_named(v2: SystemDesign):
    data = v2.to_dict()
    data["as_built"] = {"mla_rotaton_deg": 1.0}
    with pytest.raises(DesignError, match="did you mean 'mla_rotation_deg'") as error:
        design_from_dict(data)
    assert error.value.field == "as_built.mla_rotaton_deg"
