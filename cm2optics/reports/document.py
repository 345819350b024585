"""A small report: sections of text, tables and figures, written as Markdown and HTML."""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

from cm2optics.formats.atomic import write_text_atomic


@dataclass
class Report:
    """Blocks in reading order; figure paths are relative to the report's folder."""

    title: str
    blocks: list[tuple[str, object]] = field(default_factory=list)

    def heading(self, text: str) -> None:
        self.blocks.append(("h2", text))

    def paragraph(self, text: str) -> None:
        self.blocks.append(("p", text))

    def table(self, header: list[str], rows: list[list[object]]) -> None:
        self.blocks.append(("table", (header, rows)))

    def figure(self, path: str, caption: str) -> None:
        self.blocks.append(("figure", (path, caption)))

    def to_markdown(self) -> str:
        lines = [f"# {self.title}", ""]
        for kind, content in self.blocks:
            if kind == "h2":
                lines += [f"## {content}", ""]
            elif kind == "p":
                lines += [str(content), ""]
            elif kind == "table":
                header, rows = content
                lines.append("| " + " | ".join(header) + " |")
                lines.append("|" + "---|" * len(header))
                lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
                lines.append("")
            elif kind == "figure":
                path, caption = content
                lines += [f"![{caption}]({path})", "", f"*{caption}*", ""]
        return "\n".join(lines)

    def to_html(self) -> str:
        parts = [
            "<!doctype html><html><head><meta charset='utf-8'>",
            f"<title>{html.escape(self.title)}</title>",
            "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em}"
            "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
            "th{background:#f0f0f0}td:first-child{text-align:left}figure{margin:1em 0}img{max-width:100%}"
            "figcaption{color:#555;font-size:90%}</style></head><body>",
            f"<h1>{html.escape(self.title)}</h1>",
        ]
        for kind, content in self.blocks:
            if kind == "h2":
                parts.append(f"<h2>{html.escape(str(content))}</h2>")
            elif kind == "p":
                parts.append(f"<p>{html.escape(str(content))}</p>")
            elif kind == "table":
                header, rows = content
                parts.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>")
                parts += ["<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows]
                parts.append("</table>")
            elif kind == "figure":
                path, caption = content
                parts.append(
                    f"<figure><img src='{html.escape(path)}' alt='{html.escape(caption)}'><figcaption>{html.escape(caption)}</figcaption></figure>"
                )
        parts.append("</body></html>")
        return "\n".join(parts)

    def write(self, folder: Path) -> Path:
        """Write ``report.md`` and ``report.html`` into ``folder``; return the HTML path."""
        folder = Path(folder)
        write_text_atomic(folder / "report.md", self.to_markdown())
        return write_text_atomic(folder / "report.html", self.to_html())
