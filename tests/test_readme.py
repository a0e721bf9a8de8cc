"""README.md describes this repository and nothing outside it: every path it names in
backticks that looks like a repository path exists, and it points at no file a user who clones
the repository does not get (a shared folder beside the checkout, a SPEC.md that is not here)."""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
#: Folders that hold what a run or a build produces, not part of the checkout.
GENERATED = {"runs", ".venv", "build"}


def _inline_code(text: str) -> list[str]:
    """The `inline code` spans of Markdown text, fenced blocks left out (they hold commands
    and YAML whose paths are relative to other folders)."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.MULTILINE | re.DOTALL)
    return re.findall(r"`([^`\n]+)`", prose)


def _top_level() -> set[str]:
    return {p.name for p in ROOT.iterdir() if p.name not in GENERATED and p.name != ".git"}


def repository_paths(text: str) -> list[str]:
    """The spans that name a path in the repository: relative, no placeholder (`<id>`), no
    spaces, and either under a top-level entry of the repository or a folder path with a file
    extension (`scenarios/traces/x.csv`)."""
    top = _top_level()
    paths = []
    for span in _inline_code(text):
        if " " in span or "<" in span or span.startswith(("/", "~", "-")):
            continue
        first = span.split("/", 1)[0]
        if first in GENERATED:
            continue
        looks_like_file = "/" in span and re.search(r"\.[A-Za-z0-9]+$", span) is not None
        if (first in top and ("/" in span or "." in span)) or looks_like_file:
            paths.append(span)
    return paths


def _in_repository(name: str) -> bool:
    """Whether a file called `name` is anywhere in the checkout (what a run or the venv made
    does not count)."""
    for _folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in GENERATED and d != ".git"]
        if name in files:
            return True
    return False


#: Markdown files the README names that a run or a sweep writes, not the repository.
RUN_OUTPUTS = {"report.md", "sweep.md"}


def test_readme_names_no_file_outside_the_repository() -> None:
    text = README.read_text()
    assert "../" not in text, "README points outside the checkout"
    assert "shared folder" not in text and "/work/" not in text
    for name in set(re.findall(r"\b[A-Za-z][\w-]*\.md\b", text)) - RUN_OUTPUTS:
        assert _in_repository(name), f"README names {name}, which the repository does not have"


def test_every_repository_path_the_readme_names_exists() -> None:
    paths = repository_paths(README.read_text())
    assert len(paths) >= 30, paths  # the check must be looking at something
    missing = [p for p in paths if not (ROOT / p).exists()]
    assert not missing, f"README names paths the repository does not have: {missing}"


def test_markdown_links_inside_the_repository_exist() -> None:
    for target in re.findall(r"\]\(([^)\s]+)\)", README.read_text()):
        if not re.match(r"[a-z]+:", target) and not target.startswith("#"):
            assert (ROOT / target).exists(), f"README links to {target}, which is not here"


def test_the_path_filter_finds_paths_and_leaves_the_rest() -> None:
    text = (
        "`netem/tc.py` `nodes/ros/` `scenarios/traces/uplink-steps.csv` `elsewhere/thing.yaml` "
        "`runs/<id>/run.mcap` `.venv/bin/testbed` `links.air.uplink.delay` `/run/netns` "
        "`sensor_msgs/msg/Image` `python -m netem.relay` `report.html`\n"
        "```sh\ncat `traces/not_checked.csv`\n```\n"
    )
    assert repository_paths(text) == [
        "netem/tc.py",
        "nodes/ros/",
        "scenarios/traces/uplink-steps.csv",
        "elsewhere/thing.yaml",
    ]
