"""Fixtures the reconstruction tests share."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def lsv_model_path(tmp_path_factory) -> Path:
    """A small LSV model file (analytic PSF scan binned 8×, 1.2-mm lateral step), built once per session."""
    from cm2optics.design import load_preset
    from cm2optics.lsv.toy import analytic_lsv_model_file

    path = tmp_path_factory.getbasetemp() / "shared-lsv-b8.h5"
    return analytic_lsv_model_file(path, load_preset("cm2-v2"), binning=8, rank=6, lateral_nodes=7, depth_nodes=3)


@pytest.fixture(scope="session")
def lsv_model(lsv_model_path):
    """The model of :func:`lsv_model_path`, loaded."""
    from cm2optics.lsv.model import load_model

    return load_model(lsv_model_path)


@pytest.fixture(scope="module")
def one_torch_thread():
    """Torch on one thread for a module's tests (small nets run faster so on two shared cores)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
