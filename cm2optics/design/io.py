"""The design's YAML edge: load and validate a design file or a shipped preset."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from cm2optics.design.coerce import dataclass_from_dict
from cm2optics.design.system import SystemDesign
from cm2optics.design.validation import DesignError

__all__ = ["DEFAULT_PRESET", "available_presets", "default_design", "design_from_dict", "load_design", "load_preset"]

#: The preset that stands in where a function is given no design (the paper's device).
DEFAULT_PRESET = "cm2-v2"


def design_from_dict(data: dict[str, Any]) -> SystemDesign:
    """Build and validate a :class:`SystemDesign` from plain data (as parsed from YAML)."""
    return dataclass_from_dict(SystemDesign, data, "")


def load_design(path: str | Path) -> SystemDesign:
    """Load and validate a design YAML file."""
    path = Path(path)
    if not path.is_file():
        raise DesignError("design", str(path), "no such file")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise DesignError("design", str(path), f"is not valid YAML ({error})") from None
    return design_from_dict(data)


def available_presets() -> list[str]:
    """Names of the presets shipped with the package."""
    folder = resources.files("cm2optics.design") / "presets"
    return sorted(p.name.removesuffix(".yaml") for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_preset(name: str) -> SystemDesign:
    """Load a shipped preset by name (``cm2-v2``, ``cm2-v1``) or a YAML path."""
    if name.endswith((".yaml", ".yml")):
        return load_design(name)
    presets = available_presets()
    if name not in presets:
        raise DesignError("preset", name, f"unknown preset; available: {', '.join(presets)} (or a path to a .yaml)")
    text = (resources.files("cm2optics.design") / "presets" / f"{name}.yaml").read_text()
    return design_from_dict(yaml.safe_load(text))


@lru_cache(maxsize=1)
def default_design() -> SystemDesign:
    """The :data:`DEFAULT_PRESET` design, loaded once: what a function given no design falls back on."""
    return load_preset(DEFAULT_PRESET)
