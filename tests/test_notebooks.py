"""Every walkthrough notebook runs top to bottom (at the small size it uses by default)."""

from __future__ import annotations

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


#: Run only with ``-m slow``, for the default suite's 20 minutes: 08 runs the whole calibration loop
#: (≈ 110 s quiet; the loop itself is tested in the default suite by tests/calibrate, e.g.
#: ``test_calibrate_scan_end_to_end``); 06 renders and reconstructs its volumes (≈ 50 s quiet; the
#: same calls are tested by tests/synth and tests/recon, e.g. ``test_dataset_files_manifest_and_reproducibility``
#: and ``test_every_method_recovers_a_few_emitters``).
SLOW_NOTEBOOKS = {"06-synthetic-data-and-baselines.ipynb", "08-calibration.ipynb"}


@pytest.mark.parametrize(
    "path",
    [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW_NOTEBOOKS else p for p in NOTEBOOKS],
    ids=lambda p: p.name,
)
def test_notebook_runs(path: Path, tmp_path):
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(
        notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    errors = [
        o
        for cell in notebook.cells
        if cell.cell_type == "code"
        for o in cell.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors


def test_there_are_notebooks():
    assert any(p.name.startswith("01-") for p in NOTEBOOKS)
