"""Export a design's parts and assembly as STL/STEP with pictures and a ``manifest.json``.

Everything is written into a staging folder beside the destination and moved into place
only when the whole export has succeeded, so a failed or interrupted export leaves the
destination as it was.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cadquery as cq
import trimesh
from rich.progress import Progress

import cm2optics
from cm2optics.cad.assembly import PartSpec, PlacedPart, fits, interferences, part_specs, place_parts
from cm2optics.cad.mesh_checks import check_mesh
from cm2optics.cad.render import render_meshes, render_part
from cm2optics.cad.tessellate import DEFAULT_TOLERANCE_UM, export_step, export_stl
from cm2optics.design import SystemDesign
from cm2optics.formats.atomic import write_json_atomic, write_text_atomic

FORMATS = ("stl", "step")
#: Relative mesh-volume error accepted for an exported part.
VOLUME_TOLERANCE = 0.005


def parse_formats(formats: str | Iterable[str]) -> tuple[str, ...]:
    """``("stl", "step")`` (or one name) checked; unknown formats raise ``ValueError``."""
    items = [formats] if isinstance(formats, str) else list(formats)  # the CLI splits "stl,step"
    parsed = tuple(dict.fromkeys(f.strip().lower() for f in items if f.strip()))
    bad = [f for f in parsed if f not in FORMATS]
    if not parsed or bad:
        raise ValueError(f"--format {','.join(items)!s}: allowed formats are {', '.join(FORMATS)} (comma-separated)")
    return parsed


def _part_record(
    design: SystemDesign,
    spec: PartSpec,
    shape: cq.Solid,
    files: dict[str, str],
    mesh: trimesh.Trimesh,
    count: int,
    wall_samples: int,
) -> dict[str, Any]:
    min_wall_mm = design.mechanics.min_wall_mm
    report = check_mesh(mesh, wall_samples)
    exact = shape.Volume()
    volume_error = abs(report.volume_mm3 - exact) / exact
    fidelity = {k: round(v, 4) for k, v in spec.fidelity(design, mesh).items()} if spec.fidelity else {}
    return {
        "name": spec.name,
        "file": files.get("stl") or next(iter(files.values())),
        "files": files,
        "description": spec.description,
        "material": spec.material,
        "printed": spec.printed,
        "count": count,
        "volume_mm3": round(exact, 4),
        "mesh_volume_mm3": round(report.volume_mm3, 4),
        "volume_error": round(volume_error, 6),
        "bbox_mm": [[round(v, 4) for v in report.bbox_mm[0]], [round(v, 4) for v in report.bbox_mm[1]]],
        "watertight": report.watertight and report.winding_consistent,
        "min_wall_mm": round(report.min_wall_mm, 4),
        "printable": (not spec.printed) or report.min_wall_mm >= min_wall_mm - 1e-6,
        "faces": report.faces,
        "png": f"{spec.name}.png",
        **fidelity,
    }


def export_design(
    design: SystemDesign,
    out_dir: str | Path,
    formats: Iterable[str] = FORMATS,
    tolerance_um: float = DEFAULT_TOLERANCE_UM,
    pictures: bool = True,
    wall_samples: int = 20000,
    show_progress: bool = True,
) -> dict[str, Any]:
    """Write every part and the assembly of ``design`` to ``out_dir``; return the manifest.

    formats: any of ``stl``, ``step``.
    tolerance_um: linear deflection of the STL tessellation, µm (0.1–100).
    pictures: also render a PNG of each part, of the assembly and of its cross-section.
    wall_samples: random surface points per part for the wall-thickness check.
    """
    formats = parse_formats(formats)
    if not 0.1 <= tolerance_um <= 100:
        raise ValueError(f"--tolerance-um {tolerance_um}: must lie within 0.1–100 µm")
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        manifest = _export_into(design, staging, formats, tolerance_um / 1000.0, pictures, wall_samples, show_progress)
        out_dir.mkdir(exist_ok=True)
        for item in staging.iterdir():
            target = out_dir / item.name
            if target.is_dir():
                shutil.rmtree(target)
            item.replace(target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return manifest


def _build_part(
    design: SystemDesign, spec: Any, folder: Path, formats: tuple[str, ...], tolerance_mm: float
) -> tuple[cq.Workplane, Any]:
    """Build one part, export it (STL at ``tolerance_mm``, STEP when asked) and load its mesh
    from the STL (which is removed again when STL is not among ``formats``)."""
    workplane = spec.build(design)
    stl = folder / f"{spec.name}.stl"
    export_stl(workplane.val(), stl, tolerance_mm)
    mesh = trimesh.load(stl, force="mesh")
    if "stl" not in formats:
        stl.unlink()
    if "step" in formats:
        export_step(workplane, folder / f"{spec.name}.step")
    return workplane, mesh


def _render_pictures(design: SystemDesign, specs: list, meshes: dict, assembly_meshes: list, folder: Path) -> None:
    """A PNG of every part, of the assembly and of its section at y = 0."""
    for spec in specs:
        render_part(meshes[spec.name], spec.material, folder / f"{spec.name}.png", f"{spec.name} — {spec.description}")
    render_meshes(assembly_meshes, folder / "assembly.png", title=f"{design.name} assembly")
    render_meshes(
        assembly_meshes,
        folder / "assembly_section.png",
        title=f"{design.name} section y = 0",
        section_normal=(0.0, 1.0, 0.0),
    )


def _export_into(
    design: SystemDesign,
    folder: Path,
    formats: tuple[str, ...],
    tolerance_mm: float,
    pictures: bool,
    wall_samples: int,
    show_progress: bool,
) -> dict[str, Any]:
    timings: dict[str, float] = {}
    specs = part_specs(design)
    built: dict[str, cq.Workplane] = {}
    records, meshes = [], {}
    with Progress(disable=not show_progress, transient=True) as progress:
        task = progress.add_task("building and exporting parts", total=len(specs) + 2)
        for spec in specs:
            start = time.perf_counter()
            built[spec.name], meshes[spec.name] = _build_part(design, spec, folder, formats, tolerance_mm)
            timings[spec.name] = time.perf_counter() - start
            progress.advance(task)
        placed = place_parts(design, built)
        counts = {spec.name: sum(p.part == spec.name for p in placed) for spec in specs}
        for spec in specs:
            progress.update(task, description=f"checking {spec.name}")
            shape = built[spec.name].val()
            files = {fmt: f"{spec.name}.{fmt}" for fmt in formats}
            records.append(_part_record(design, spec, shape, files, meshes[spec.name], counts[spec.name], wall_samples))
        progress.update(task, description="checking the assembly for interferences")
        start = time.perf_counter()
        clashes = interferences(placed)
        timings["interference_check"] = time.perf_counter() - start
        progress.advance(task)
        material = {spec.name: spec.material for spec in specs}
        assembly_meshes = [(meshes[p.part].copy().apply_transform(p.matrix), material[p.part]) for p in placed]
        assembly_files = _write_assembly(design, folder, formats, placed, assembly_meshes)
        if pictures:
            progress.update(task, description="rendering pictures")
            start = time.perf_counter()
            _render_pictures(design, specs, meshes, assembly_meshes, folder)
            timings["pictures"] = time.perf_counter() - start
        progress.advance(task)
    manifest = {
        "design": design.name,
        "parameter_hash": design.parameter_hash(),
        "package_version": cm2optics.__version__,
        "tolerance_um": round(tolerance_mm * 1000.0, 6),
        "formats": list(formats),
        "parts": records,
        "assembly": {
            "files": assembly_files,
            "file": assembly_files.get("stl") or assembly_files.get("step"),
            "instances": [{"instance": p.instance, "part": p.part} for p in placed],
            "interferences": clashes,
            "fits": [f.as_dict() for f in fits(design)],
            "png": ["assembly.png", "assembly_section.png"] if pictures else [],
        },
        "checks": {
            "all_watertight": all(r["watertight"] for r in records),
            "volumes_within_tolerance": all(r["volume_error"] <= VOLUME_TOLERANCE for r in records),
            "all_printable": all(r["printable"] for r in records),
            "no_interferences": not clashes,
        },
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
    }
    write_json_atomic(folder / "manifest.json", manifest)
    write_text_atomic(folder / "README.md", parts_readme(design, manifest))
    design.save(folder / "design.yaml")
    return manifest


def size_text(bbox_mm: list[list[float]]) -> str:
    """``[[x0, y0, z0], [x1, y1, z1]]`` → ``"dx × dy × dz"`` (mm, two decimals)."""
    lower, upper = bbox_mm
    return " × ".join(f"{high - low:.2f}" for low, high in zip(lower, upper, strict=True))


def parts_readme(design: SystemDesign, manifest: dict[str, Any]) -> str:
    """A README for the exported folder: what each file is, how to print and assemble."""
    lines = [
        f"# Parts of `{design.name}`",
        "",
        f"Exported by cm2optics {manifest['package_version']} from `design.yaml` (parameter hash "
        f"`{manifest['parameter_hash']}`) with an STL chord tolerance of {manifest['tolerance_um']} µm. "
        f"Regenerate with `cm2 cad export --preset design.yaml --out <folder>`; `manifest.json` holds every number below.",
        "",
        "Each part file is in the part's own frame; `assembly.*` places every instance in the device frame "
        "(origin on the sensor surface, +z towards the sample, mm).",
        "",
        "| file | part | n | kind | material | volume mm³ | size mm | min wall mm | watertight |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for part in manifest["parts"]:
        size = size_text(part["bbox_mm"])
        kind = "print" if part["printed"] else "buy / cut"
        lines.append(
            f"| `{part['file']}` | {part['description']} | {part['count']} | {kind} | {part['material']} | "
            f"{part['volume_mm3']:.3f} | {size} | {part['min_wall_mm']:.3f} | {'yes' if part['watertight'] else 'NO'} |"
        )
    lines += [
        "",
        "## Printing",
        f"Printed parts need walls ≥ {design.mechanics.min_wall_mm} mm (all pass: see *min wall*). Print the housings in black "
        "resin (light-tight), the collimators in clear resin and varnish their outer TIR surface with a thin coat of diluted "
        "clear resin for optical smoothness, as the original authors did. Seats are sized for "
        f"{design.mechanics.clearance_mm} mm clearance per side; adjust `mechanics.clearance_mm` (0.05–0.2) to your printer.",
        "",
        "## Fits",
        "",
        "| seated part | seat | clearance mm |",
        "|---|---|---|",
    ]
    lines += [f"| {f['part']} | {f['seat']} | {f['clearance_mm']} |" for f in manifest["assembly"]["fits"]]
    clashes = manifest["assembly"]["interferences"]
    lines += ["", f"Interfering solids in the assembly: {'none' if not clashes else clashes}.", ""]
    return "\n".join(lines)


def _write_assembly(
    design: SystemDesign,
    folder: Path,
    formats: tuple[str, ...],
    placed: list[PlacedPart],
    meshes: list[tuple[trimesh.Trimesh, str]],
) -> dict[str, str]:
    files = {}
    if "stl" in formats:
        trimesh.util.concatenate([m for m, _ in meshes]).export(folder / "assembly.stl")
        files["stl"] = "assembly.stl"
    if "step" in formats:
        assembly = cq.Assembly(name=design.name)
        for p in placed:
            assembly.add(cq.Workplane().add(p.solid), name=p.instance)
        assembly.export(str(folder / "assembly.step"), exportType="STEP")
        files["step"] = "assembly.step"
    return files
