"""The design is the leaf and optics sits right above it (DESIGN.md): checked by reading imports."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cm2optics"

#: Subpackage → the cm2optics subpackages its modules may import (besides itself).
ALLOWED = {"design": set(), "optics": {"design"}}


def _cm2_imports(path: Path) -> set[str]:
    """The cm2optics subpackages (or top-level modules) that ``path`` imports, lazily or not."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            modules = [node.module]
        else:
            continue
        names |= {m.split(".")[1] for m in modules if m.startswith("cm2optics.")}
    return names


@pytest.mark.parametrize(
    "module",
    sorted(p for room in ALLOWED for p in (PACKAGE / room).rglob("*.py")),
    ids=lambda p: str(p.relative_to(PACKAGE)),
)
def test_design_and_optics_import_only_below_them(module: Path):
    room = module.relative_to(PACKAGE).parts[0]
    extra = _cm2_imports(module) - ALLOWED[room] - {room}
    assert not extra, f"{module.relative_to(PACKAGE)} imports cm2optics.{sorted(extra)}; {room}/ may import only {ALLOWED[room] or 'nothing'}"
