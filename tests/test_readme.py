"""README.md describes this repository and nothing outside it: every path it names in
backticks that looks like a repository path exists, and it points at no file a user who clones
the repository does not get (a shared folder beside the checkout, a SPEC.md that is not here).
Every YAML example in it is a scenario fragment that the loader accepts, laid over the library
scenario that the comment above it names: a user copies these."""

from __future__ import annotations

import copy
import os
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from testbed.scenario import loads
from testbed.scenario.issues import ScenarioError

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
SCENARIOS = ROOT / "scenarios"
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


def broken_links(text: str) -> tuple[list[str], list[str]]:
    """(every markdown link target of `text`, the ones inside the repository that are not
    there); an anchor must be one of the text's headings, as GitHub spells them."""
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    anchors = {
        re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
        for h in re.findall(r"^#+ (.+)$", text, flags=re.MULTILINE)
    }
    broken = []
    for target in targets:
        if re.match(r"[a-z]+:", target):
            continue  # a web address: not checked offline
        if target.startswith("#"):
            if target[1:] not in anchors:
                broken.append(target)
        elif not (ROOT / target).exists():
            broken.append(target)
    return targets, broken


def test_markdown_links_inside_the_repository_exist() -> None:
    targets, broken = broken_links(README.read_text())
    assert targets, "the link pattern found no link in the README"
    assert not broken, f"README links to what is not here: {broken}"
    # and the check bites: a missing file and an unknown anchor, beside ones that exist
    text = (
        "# Reports\n[a](Makefile) [b](nowhere/x.md) [c](#reports) [d](#nothing) [e](https://x.y)\n"
    )
    assert broken_links(text) == (
        ["Makefile", "nowhere/x.md", "#reports", "#nothing", "https://x.y"],
        ["nowhere/x.md", "#nothing"],
    )


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


# ---- YAML examples ---------------------------------------------------------------------------

#: The line right above each ```yaml fence: the library scenario the example is laid over.
BASE_COMMENT = re.compile(
    r"<!-- validated over (scenarios/[\w.-]+\.yaml) \(tests/test_readme\.py\) -->"
)


def yaml_examples(text: str) -> list[tuple[int, str | None, str]]:
    """(line of the fence, the scenario named in the comment above it or None, the YAML) per
    ```yaml block of Markdown text."""
    lines = text.splitlines()
    out = []
    for m in re.finditer(r"^```yaml\n(.*?)^```", text, flags=re.MULTILINE | re.DOTALL):
        line = text.count("\n", 0, m.start()) + 1
        above = BASE_COMMENT.fullmatch(lines[line - 2]) if line >= 2 else None
        out.append((line, above.group(1) if above else None, m.group(1)))
    return out


def laid_over(base: dict[str, Any], fragment: dict[str, Any]) -> dict[str, Any]:
    """`fragment` laid over `base`: mappings merge key by key, anything else replaces."""
    out = copy.deepcopy(base)
    for key, value in fragment.items():
        below = out.get(key)
        if isinstance(value, dict) and isinstance(below, dict):
            out[key] = laid_over(below, value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def check_example(base_file: Path, fragment_text: str) -> None:
    """Raise ScenarioError when the fragment over the base scenario is refused by the loader
    (paths in it resolve against scenarios/, as the library's own do)."""
    fragment = yaml.safe_load(fragment_text)
    assert isinstance(fragment, dict), "a scenario fragment is a mapping"
    tree = laid_over(yaml.safe_load(base_file.read_text(encoding="utf-8")), fragment)
    loads(
        yaml.safe_dump(tree, sort_keys=False),
        source=f"<README over {base_file.name}>",
        base_dir=SCENARIOS,
    )


EXAMPLES = yaml_examples(README.read_text())


def test_the_readme_has_yaml_examples_and_each_names_its_base_scenario() -> None:
    assert len(EXAMPLES) >= 7, EXAMPLES
    unnamed = [line for line, base, _ in EXAMPLES if base is None]
    assert not unnamed, (
        f"README.md lines {unnamed}: a ```yaml example needs the line "
        "'<!-- validated over scenarios/<file>.yaml (tests/test_readme.py) -->' right above it"
    )


@pytest.mark.parametrize(
    ("base", "fragment"),
    [(base, fragment) for _, base, fragment in EXAMPLES if base],
    ids=[f"line{line}" for line, base, _ in EXAMPLES if base],
)
def test_every_yaml_example_is_accepted_over_its_base_scenario(base: str, fragment: str) -> None:
    try:
        check_example(ROOT / base, fragment)
    except ScenarioError as err:
        pytest.fail(f"README's example over {base} is refused:\n{err}", pytrace=False)


def test_the_example_check_bites_and_merges_mappings_only() -> None:
    # two UEs of one cell on different slot grids: what an earlier example in the README did
    with pytest.raises(ScenarioError, match="slot grid of cell gnb1"):
        check_example(
            SCENARIOS / "multi_vehicle.yaml",
            "links:\n  air: {radio: oai-tdd-30k}\n  overrides:\n"
            "    - {link: av2-gnb1, uplink: {radio: {profile: srsran-lowlat}}}\n",
        )
    merged = laid_over({"a": {"b": 1, "c": [1]}, "d": 2}, {"a": {"c": [2]}, "e": 3})
    assert merged == {"a": {"b": 1, "c": [2]}, "d": 2, "e": 3}
