"""Output for people: rich in a terminal, plain lines in CI or when piped."""

from __future__ import annotations

import os
import sys

from rich.console import Console
from rich.table import Table

_plain = bool(os.environ.get("CI")) or not sys.stdout.isatty()
out = Console(no_color=_plain, highlight=False, soft_wrap=True)
err = Console(
    stderr=True, no_color=_plain or not sys.stderr.isatty(), highlight=False, soft_wrap=True
)


def is_plain() -> bool:
    """Whether output is plain lines (CI, a pipe): no colours, no live displays."""
    return _plain


def plain(text: str) -> None:
    out.print(text, markup=False)


def ok(text: str) -> None:
    out.print(text, markup=False, style=None if _plain else "green")


def warn(text: str) -> None:
    err.print(f"warning: {text}", markup=False, style=None if _plain else "yellow")


def error(text: str) -> None:
    err.print(f"error: {text}", markup=False, style=None if _plain else "bold red")


def table(headers: list[str], rows: list[list[str]]) -> None:
    if _plain:
        widths = [
            max(len(h), *(len(r[i]) for r in rows)) if rows else len(h)
            for i, h in enumerate(headers)
        ]
        plain("  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)).rstrip())
        for row in rows:
            plain("  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
        return
    t = Table(*headers)
    for row in rows:
        t.add_row(*row)
    out.print(t)
