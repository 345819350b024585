"""The operator of a model file for the baselines: the 3D-LSV operator or the depth-wise LSI one.

Operators follow :class:`cm2optics.formats.operator.VolumeOperator`; the 3D-LSV operator is
:class:`cm2optics.lsv.operators.LSVOperator`, the depth-wise LSI one (the V1 paper's model)
:class:`cm2optics.lsv.lsi.DepthwiseConvOperator`. Files are read by
:func:`cm2optics.formats.models.load_forward_model`: an LSV model (``format = "cm2optics-lsv"``)
or a PSF stack (``format = "cm2optics-psf-stack"``).
"""

from __future__ import annotations

from pathlib import Path

from cm2optics.formats.models import load_forward_model
from cm2optics.formats.operator import VolumeOperator
from cm2optics.formats.volume import VolumeGrid
from cm2optics.lsv.lsi import DepthwiseConvOperator, lsi_from_model

__all__ = ["load_operator"]


def load_operator(
    path: str | Path, grid: VolumeGrid | None = None, *, forward: str = "lsv", device: str = "cpu"
) -> VolumeOperator:
    """The operator of a model file on ``grid`` (default: the model's own grid).

    forward: ``"lsv"`` (the 3D-LSV operator) or ``"lsi"`` (the depth-wise LSI model derived
    from it). A PSF-stack file is depth-wise LSI already and serves both.
    """
    if forward not in ("lsv", "lsi"):
        raise ValueError(f"forward = {forward!r}: must be 'lsv' or 'lsi'")
    model = load_forward_model(path, device=device)
    if isinstance(model, DepthwiseConvOperator):
        if grid is not None and (grid.shape != model.grid.shape or grid.voxel_um != model.grid.voxel_um):
            raise ValueError(f"{path}: a PSF stack is defined on its own grid {model.grid.shape}; got {grid.shape}")
        return model
    if forward == "lsi":
        return lsi_from_model(model, grid, device=device)
    return model.operator(grid or model.default_grid, device=device)
