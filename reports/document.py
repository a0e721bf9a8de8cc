"""A report as a small document tree (sections of paragraphs, tables, figures, code), and its
Markdown rendering. `reports.html` renders the same tree as one self-contained HTML file, so
both formats always say the same thing."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Plot:
    """A figure `reports.plots` drew: the document names it, the renderers embed it."""

    file: str  # name inside the plots folder
    title: str
    caption: str


@dataclass(frozen=True)
class Para:
    text: str
    kind: str = "text"  # "text", "warning" (shown highlighted), "note"


@dataclass(frozen=True)
class Table:
    headers: list[str]
    rows: list[list[str]]
    caption: str = ""
    #: Columns whose cells are paths relative to the report (a capture file): shown as links.
    link_columns: tuple[int, ...] = ()


@dataclass(frozen=True)
class Code:
    text: str
    caption: str = ""


@dataclass(frozen=True)
class Image:
    plot: Plot


Block = Para | Table | Code | Image


@dataclass
class Section:
    title: str
    blocks: list[Block] = field(default_factory=list)
    anchor: str = ""

    def add(self, *blocks: Block) -> Section:
        self.blocks.extend(blocks)
        return self


@dataclass
class Document:
    title: str
    headline: str
    sections: list[Section] = field(default_factory=list)


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def to_markdown(doc: Document, plots_dir: str = "plots") -> str:
    """Markdown with figures linked from `plots_dir` (relative to the report)."""
    out = [f"# {doc.title}", "", f"**{doc.headline}**", ""]
    for s in doc.sections:
        out += [f"## {s.title}", ""]
        for b in s.blocks:
            if isinstance(b, Para):
                prefix = {"warning": "> **Warning:** ", "note": "> "}.get(b.kind, "")
                out += [prefix + b.text, ""]
            elif isinstance(b, Table):
                if b.caption:
                    out += [f"*{b.caption}*", ""]
                out.append("| " + " | ".join(_md_cell(h) for h in b.headers) + " |")
                out.append("|" + "|".join(" --- " for _ in b.headers) + "|")
                out += [
                    "| "
                    + " | ".join(
                        f"[{_md_cell(c)}]({c})" if i in b.link_columns else _md_cell(c)
                        for i, c in enumerate(row)
                    )
                    + " |"
                    for row in b.rows
                ]
                out.append("")
            elif isinstance(b, Code):
                if b.caption:
                    out += [f"*{b.caption}*", ""]
                out += ["```text", b.text.rstrip("\n"), "```", ""]
            elif isinstance(b, Image):
                out += [
                    f"![{b.plot.title}]({plots_dir}/{b.plot.file})",
                    "",
                    f"*{b.plot.caption}*",
                    "",
                ]
    return "\n".join(out).rstrip("\n") + "\n"


__all__ = ["Block", "Code", "Document", "Image", "Para", "Section", "Table", "to_markdown"]
