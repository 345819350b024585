"""Heavy libraries stay in their rooms (DESIGN.md): checked by reading every module's imports."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cm2optics"

ROOMS = {
    "cadquery": ("cad",),
    "OCP": ("cad",),
    "mitsuba": ("optics", "illumination", "emission"),
    "drjit": ("optics", "illumination", "emission"),
    "torch": ("lsv", "synth", "recon", "calibrate"),
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("module", sorted(PACKAGE.rglob("*.py")), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_heavy_imports_stay_in_their_rooms(module: Path):
    room = module.relative_to(PACKAGE).parts[0]
    for library in _imports(module) & set(ROOMS):
        assert room in ROOMS[library], (
            f"{module.relative_to(PACKAGE)} imports {library}, which belongs in {ROOMS[library]}"
        )
