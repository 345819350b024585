"""The architecture of DESIGN.md as rules, checked by reading every module's imports.

Two kinds of rule:
- heavy libraries stay in their rooms (CadQuery only in ``cad``, Mitsuba/Dr.Jit only where rays
  are traced, torch only where tensors are needed);
- the arrows between the package's own parts point one way: no package cycles, no stage imports
  the command line or the reports, the formats and the design import no stage, the 3D-LSV model
  and the reconstruction import no ray tracer and no CAD.

The checker is a plain function of a source tree, so a test can copy the tree, add one bad
import and see the rule fail.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cm2optics"
NAME = "cm2optics"

ROOMS = {
    "cadquery": ("cad",),
    "OCP": ("cad",),
    "mitsuba": ("optics", "illumination", "emission"),
    "drjit": ("optics", "illumination", "emission"),
    "torch": ("lsv", "synth", "recon", "calibrate"),
}

TRACERS = {"emission", "illumination"}
FRONT = {"cli", "reports"}  # the command line and the reports sit on top of everything
BASE = {"errors", "__init__"}  # the error base classes and the version: below everything, imported by all

#: parts that may import only the parts named (besides the base)
ONLY: dict[str, set[str]] = {
    "design": set(),  # the leaf of parameters
    "formats": set(),  # file formats: no stage, not even the design
    "optics": {"design"},  # the pure optics core
}
#: part → parts it may never import (besides the front, forbidden to every stage)
NEVER: dict[str, set[str]] = {
    "spectra": TRACERS | {"cad", "lsv", "synth", "recon", "metrics", "calibrate"},
    "cad": TRACERS | {"spectra", "lsv", "synth", "recon", "metrics", "calibrate"},
    "lsv": TRACERS | {"cad", "recon", "metrics", "calibrate"},
    "synth": TRACERS | {"cad", "recon", "calibrate"},
    "recon": TRACERS | {"cad", "calibrate"},
    "metrics": TRACERS | {"cad", "optics", "lsv", "synth", "recon", "calibrate"},
}


def part_of(module: Path, root: Path) -> str:
    """The top-level part a module belongs to: its sub-package, or its own name at the top level."""
    parts = module.relative_to(root).parts
    return parts[0] if len(parts) > 1 else Path(parts[0]).stem


def _absolute(node: ast.ImportFrom, module: Path, root: Path) -> str | None:
    """The absolute dotted name an ``ImportFrom`` refers to (relative imports resolved)."""
    if node.level == 0:
        return node.module
    package = list(module.relative_to(root.parent).with_suffix("").parts)[:-1]  # the module's package
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(module: Path, root: Path) -> tuple[set[str], set[str]]:
    """(third-party top-level names, internal dotted names) imported anywhere in a module."""
    tree = ast.parse(module.read_text(), filename=str(module))
    external, internal = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            target = _absolute(node, module, root)
            names = [target] if target else []
            if target == NAME:  # `from cm2optics import design`
                names = [f"{NAME}.{alias.name}" for alias in node.names]
        else:
            continue
        for name in names:
            (internal if name.split(".")[0] == NAME else external).add(
                name if name.startswith(NAME) else name.split(".")[0]
            )
    return external, internal


def part_graph(root: Path) -> dict[str, set[str]]:
    """Which parts of the package import which (edges between different parts only)."""
    graph: dict[str, set[str]] = {}
    for module in sorted(root.rglob("*.py")):
        source = part_of(module, root)
        graph.setdefault(source, set())
        for name in imports_of(module, root)[1]:
            dotted = name.split(".")
            if len(dotted) > 1 and dotted[1] != source:
                graph[source].add(dotted[1])
    return graph


def forbidden_arrows(graph: dict[str, set[str]]) -> list[str]:
    """Every import arrow the architecture forbids, as readable sentences."""
    problems = []
    for source, targets in sorted(graph.items()):
        for target in sorted(targets - BASE):
            if target in FRONT and source not in FRONT:
                problems.append(f"{source} → {target}: no stage imports the command line or the reports")
                continue
            if source in ONLY and target not in ONLY[source]:
                allowed = sorted(ONLY[source]) or "nothing"
                problems.append(f"{source} → {target}: {source} may import only {allowed} (and the error base)")
            elif target in NEVER.get(source, set()):
                problems.append(f"{source} → {target}: forbidden by the architecture (ARCHITECTURE.md)")
    return problems


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of two or more parts (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return groups


def architecture_problems(root: Path) -> list[str]:
    graph = part_graph(root)
    found = forbidden_arrows(graph)
    found += [f"package cycle: {' ↔ '.join(group)}" for group in cycles(graph)]
    return found


@pytest.mark.parametrize("module", sorted(PACKAGE.rglob("*.py")), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_heavy_imports_stay_in_their_rooms(module: Path):
    room = part_of(module, PACKAGE)
    for library in imports_of(module, PACKAGE)[0] & set(ROOMS):
        assert room in ROOMS[library], (
            f"{module.relative_to(PACKAGE)} imports {library}, which belongs in {ROOMS[library]}"
        )


def test_the_package_follows_the_architecture():
    assert architecture_problems(PACKAGE) == []


def test_parts_named_by_the_rules_exist():
    parts = set(part_graph(PACKAGE))
    assert set(ONLY) | set(NEVER) | FRONT <= parts, sorted((set(ONLY) | set(NEVER) | FRONT) - parts)


def _copy(tmp_path: Path) -> Path:
    root = tmp_path / NAME
    shutil.copytree(PACKAGE, root, ignore=shutil.ignore_patterns("__pycache__", "*.yaml", "*.csv", "data"))
    return root


@pytest.mark.parametrize(
    ("module", "line", "expected"),
    [
        ("lsv/__init__.py", "from cm2optics.cli import app", "lsv → cli"),
        ("design/__init__.py", "from cm2optics.formats import outputs", "design → formats"),
        ("formats/__init__.py", "import cm2optics.lsv", "formats → lsv"),
        ("lsv/__init__.py", "from cm2optics.emission import trace", "lsv → emission"),
        ("recon/__init__.py", "from ..cad import mla", "recon → cad"),
        ("synth/__init__.py", "from cm2optics import recon", "synth → recon"),
    ],
)
def test_a_deliberately_bad_import_is_caught(tmp_path: Path, module: str, line: str, expected: str):
    root = _copy(tmp_path)
    assert architecture_problems(root) == []
    target = root / module
    target.write_text(target.read_text() + f"\n\ndef _bad():\n    {line}\n")
    problems = architecture_problems(root)
    assert any(expected in problem for problem in problems), problems


def test_an_import_back_along_an_existing_arrow_is_a_cycle(tmp_path: Path):
    root = _copy(tmp_path)
    graph = part_graph(root)
    source, target = next((s, t) for s, ts in sorted(graph.items()) for t in sorted(ts) if (root / t).is_dir())
    init = root / target / "__init__.py"
    init.write_text(init.read_text() + f"\n\ndef _bad():\n    import {NAME}.{source}\n")
    assert any("package cycle" in problem and source in problem for problem in architecture_problems(root))


def test_a_heavy_import_outside_its_room_is_caught(tmp_path: Path):
    root = _copy(tmp_path)
    bad = root / "metrics" / "_bad.py"
    bad.write_text("import mitsuba\n")
    assert "mitsuba" in imports_of(bad, root)[0] and part_of(bad, root) not in ROOMS["mitsuba"]
