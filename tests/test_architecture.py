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


def _package_imports(path: Path) -> set[str]:
    """The cm2optics sub-packages ``path`` imports (lazily or not), relative imports included."""
    tree = ast.parse(path.read_text(), filename=str(path))
    own = path.relative_to(PACKAGE).parts
    names = set()
    for node in ast.walk(tree):
        modules = []
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level:
            base = own[: len(own) - node.level]
            modules = [".".join(("cm2optics", *base, *(node.module.split(".") if node.module else [])))]
        elif isinstance(node, ast.ImportFrom) and node.module:
            modules = [node.module]
            if node.module == "cm2optics":  # from cm2optics import lsv
                modules = [f"cm2optics.{alias.name}" for alias in node.names]
        for module in modules:
            parts = module.split(".")
            if parts[0] == "cm2optics" and len(parts) > 1 and (PACKAGE / parts[1]).is_dir():
                names.add(parts[1])
    return names


def package_graph() -> dict[str, set[str]]:
    """Sub-package → the sub-packages it imports (itself excluded)."""
    graph: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE).parts
        if len(parts) < 2:
            continue
        graph.setdefault(parts[0], set()).update(_package_imports(path) - {parts[0]})
    return graph


def _cycle(graph: dict[str, set[str]], nodes: set[str]) -> list[str] | None:
    def visit(node: str, path: list[str]) -> list[str] | None:
        for nxt in sorted(graph.get(node, ()) & nodes):
            if nxt in path:
                return path[path.index(nxt) :] + [nxt]
            found = visit(nxt, path + [nxt])
            if found:
                return found
        return None

    for start in sorted(nodes):
        found = visit(start, [start])
        if found:
            return found
    return None


def test_stages_import_no_cycle():
    """lsv, synth, recon, metrics and emission import each other in one direction only."""
    cycle = _cycle(package_graph(), {"lsv", "synth", "recon", "metrics", "emission", "formats"})
    assert cycle is None, "package cycle: " + " → ".join(cycle)


def test_synth_does_not_import_recon():
    assert "recon" not in package_graph()["synth"]


def test_formats_imports_no_stage():
    """formats is a leaf (DESIGN.md): only numpy, tifffile, h5py, yaml and the standard library."""
    assert package_graph()["formats"] == set()
    for path in (PACKAGE / "formats").glob("*.py"):
        assert not _imports(path) & {"torch", "mitsuba", "drjit", "cadquery", "typer", "rich"}, path.name
