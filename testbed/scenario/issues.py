"""What is wrong with a scenario file: one `Issue` per problem, all of them in a `ScenarioError`,
and the one "did you mean ...?" hint both the schema's kinds and the loader's rules give."""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass

from testbed.errors import BadInput

ROOT_PATH = "(top level)"


@dataclass(frozen=True)
class Issue:
    """One problem, located in a file (line and column are 1-based; None when unknown).

    `path` names the field the way an author reads the YAML (`topology.vehicles[1].gnb`);
    `expected` and `found` are phrases ("a rate like 20mbit", "'20mbps'"); `hint` is an
    optional suggestion ("did you mean 'jitter'?").
    """

    file: str
    line: int | None
    column: int | None
    path: str
    expected: str
    found: str
    hint: str | None = None

    def location(self) -> str:
        if self.line is None:
            return self.file
        return f"{self.file}:{self.line}:{self.column or 1}"

    def __str__(self) -> str:
        where = f"{self.location()}: {self.path}:" if self.path else f"{self.location()}:"
        text = f"{where} expected {self.expected}, found {self.found}"
        return f"{text}; {self.hint}" if self.hint else text


class ScenarioError(BadInput):
    """A scenario file is wrong. `str()` lists every issue, one per line; exit code 2."""

    def __init__(self, issues: list[Issue]) -> None:
        self.issues: tuple[Issue, ...] = tuple(issues)
        super().__init__("\n".join(str(issue) for issue in self.issues))


def did_you_mean(
    word: str, choices: Sequence[str], cutoff: float, *, any_case: bool = False
) -> str | None:
    """The hint "did you mean 'x'?" for the choice closest to `word` (difflib ratio at least
    `cutoff`), or None. `any_case`: also suggest `word` in lower case when that is a choice
    (difflib compares case, so `SET` finds no `set`)."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=cutoff)
    if not close and any_case and word.lower() in choices:
        close = [word.lower()]
    return f"did you mean {close[0]!r}?" if close else None
