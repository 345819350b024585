"""Forward-model files: what a file is, and one loader for all of them.

Two formats are forward models: the 3D-LSV model file (:mod:`cm2optics.formats.lsv_model`,
from ``cm2 lsv build``) and the PSF stack of a depth-wise LSI model, which is also how the
analytic test / fast-fallback model is saved (:mod:`cm2optics.formats.psf_stack`).
:func:`load_forward_model` reads the format from the file and hands it to the class that owns
it. The owners live in stages (torch), which this package must not import: they are named
here as ``module:attribute`` strings and imported when a file of theirs is loaded.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from cm2optics.formats.errors import FormatError
from cm2optics.formats.lsv_model import FORMAT as LSV_FORMAT
from cm2optics.formats.psf_stack import PSF_STACK_FORMAT
from cm2optics.formats.volume import VolumeGrid

__all__ = ["LOADERS", "ModelFormatError", "load_forward_model", "model_format", "model_grid"]

#: format → the loader (``module:callable``) that turns such a file into a forward model, and
#: whether it places the model on a torch device (an LSV model makes its operators per device).
LOADERS = {
    LSV_FORMAT: ("cm2optics.lsv.model:load_model", False),
    PSF_STACK_FORMAT: ("cm2optics.lsv.lsi:DepthwiseConvOperator.load", True),
}


class ModelFormatError(FormatError):
    """A file that is not a forward model this package reads."""


def _attrs(path: Path) -> dict[str, Any]:
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as data:
                return json.loads(str(data["attrs"])) if "attrs" in data.files else {}
        except Exception as error:  # numpy raises several types for corrupt files
            raise ModelFormatError(f"{path}: not a readable NPZ model file ({error})") from None
    try:
        with h5py.File(path, "r") as f:
            return dict(f.attrs)
    except OSError:
        raise ModelFormatError(
            f"{path}: not an HDF5 model file (an LSV model from `cm2 lsv build`, or a PSF stack)"
        ) from None


def model_format(path: str | Path) -> str:
    """The ``format`` of a model file ("" when it has none)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such model file")
    return str(_attrs(path).get("format", ""))


def model_grid(path: str | Path) -> VolumeGrid | None:
    """The volume grid a model file is defined on (its default grid), read from the header."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such model file")
    attrs = _attrs(Path(path))
    text = attrs.get("default_grid") if attrs.get("format") == LSV_FORMAT else attrs.get("grid")
    return VolumeGrid.from_dict(json.loads(text)) if text else None


def load_forward_model(path: str | Path, *, device: str = "cpu") -> Any:
    """The forward model of a file: an ``LSVModel`` for an LSV model file, a
    ``DepthwiseConvOperator`` (on ``device``) for a PSF stack. An unknown format raises
    :class:`ModelFormatError` naming the file."""
    kind = model_format(path)
    if kind not in LOADERS:
        expected = " or ".join(LOADERS)
        raise ModelFormatError(f"{path}: unknown model format {kind!r} (expected {expected})")
    target, takes_device = LOADERS[kind]
    module, _, attribute = target.partition(":")
    loader: Any = importlib.import_module(module)
    for name in attribute.split("."):
        loader = getattr(loader, name)
    return loader(path, device=device) if takes_device else loader(path)
