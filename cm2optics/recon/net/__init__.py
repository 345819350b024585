"""CM²Net: learned 3-D reconstruction for the CM² (Xue et al., Optica 2022, Section 2.3–2.5).

- :mod:`~cm2optics.recon.net.config`: :class:`NetConfig` (frozen, validated, YAML, hash).
- :mod:`~cm2optics.recon.net.refocus`: shift-and-add refocusing, its planes and shifts from the
  forward model's geometry.
- :mod:`~cm2optics.recon.net.model`: the network (demixing, view synthesis, enhancement, fusion).
- :mod:`~cm2optics.recon.net.loss`: BCE on the demixed views and the volume (weighted, focal).
- :mod:`~cm2optics.recon.net.data`: patches made on the fly, seeded per sample; curriculum.
- :mod:`~cm2optics.recon.net.train`: ``train_one_epoch``, ``evaluate``, ``train`` (checkpoints,
  exact resume, DDP); ``python -m cm2optics.recon.net.train CONFIG [--resume]``.
- :mod:`~cm2optics.recon.net.weights`: safetensors + config + model card + SHA-256.
- :mod:`~cm2optics.recon.net.infer`: :func:`reconstruct_with_net`, full field in one pass.

Imports are lazy: ``import cm2optics.recon.net`` does not load torch until a name is used.
"""

from __future__ import annotations

import importlib
from typing import Any

_NAMES = {
    "NetConfig": "config",
    "ConfigError": "config",
    "load_config": "config",
    "CM2Net": "model",
    "build_net": "model",
    "RefocusPlanes": "refocus",
    "refocus_planes": "refocus",
    "train": "train",
    "train_one_epoch": "train",
    "evaluate": "train",
    "save_weights": "weights",
    "load_weights": "weights",
    "WeightsError": "weights",
    "NetInputError": "weights",
    "GeometryMismatchError": "weights",
    "NetResult": "infer",
    "reconstruct_with_net": "infer",
    "views_from_measurement": "infer",
    "histogram_match": "infer",
}

__all__ = sorted(_NAMES)


def __getattr__(name: str) -> Any:
    if name in _NAMES:
        return getattr(importlib.import_module(f"{__name__}.{_NAMES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
