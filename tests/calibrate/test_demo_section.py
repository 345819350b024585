"""`cm2 demo` section 9: an MLA rotation injected into a traced scan, found by the loop untold."""

from __future__ import annotations

import pytest

from cm2optics.formats.scan import read_scan
from cm2optics.reports.calibration_demo import DEMO_INJECTION, add_calibration_section
from cm2optics.reports.document import Report


@pytest.mark.slow
def test_the_demo_section_finds_the_rotation_it_injected(v2, tmp_path):
    report = Report("demo")
    doc = add_calibration_section(report, v2, tmp_path)
    assert "mla_rotation" not in str(read_scan(tmp_path / "calibration-scan").meta.extra)  # nobody told it
    assert [e["name"] for e in doc["effects"]] == ["mla_rotation"]
    effect = doc["effects"][0]
    assert effect["parameters"]["angle_deg"] == pytest.approx(DEMO_INJECTION["mla_rotation_deg"], abs=0.05)
    assert effect["uncertainties"]["angle_deg"] < 0.05
    assert doc["nmse_after"] * 5 <= doc["nmse_before"] and doc["chi2_after"] <= 1.2
    assert doc["unexplained"] == []
    for figure in ("residual_montage.png", "field_maps.png"):
        assert (tmp_path / "calibration" / figure).is_file()
    assert any(kind == "figure" and "calibration/" in content[0] for kind, content in report.blocks)
