"""The house's layers (pyproject's import-linter contracts, run by `make lint`): the tree keeps
them, and the check really fails on an upward import, TYPE_CHECKING ones included, between the
packages and between netem's wings.

The broken trees are copies of the packages in a temporary folder with one import added, put
first on the path of a fresh `lint-imports` process, so the real tree is never touched."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("testbed", "netem", "nodes", "reports")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")

pytestmark = pytest.mark.skipif(
    not LINT_IMPORTS.exists(), reason="import-linter is not installed (`make setup` installs it)"
)


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache", str(root / "pyproject.toml")],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _copy_tree(tmp: Path) -> Path:
    root = tmp / "tree"
    for pkg in PACKAGES:
        shutil.copytree(
            REPO / pkg, root / pkg, ignore=shutil.ignore_patterns("__pycache__", "*.pt", "*.csv")
        )
    shutil.copy(REPO / "pyproject.toml", root / "pyproject.toml")
    return root


def test_the_tree_keeps_its_layers(tmp_path: Path) -> None:
    out = _lint(_copy_tree(tmp_path))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "3 kept, 0 broken" in out.stdout


@pytest.mark.parametrize(
    ("module", "added", "says"),
    [
        ("netem/profile.py", "from testbed.errors import BadInput", "netem.profile -> testbed"),
        (
            "nodes/edgeloc/kalman.py",
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from reports import build",
            "nodes.edgeloc.kalman -> reports",
        ),
        ("reports/html.py", "import testbed.cli", "reports.html -> testbed.cli"),
        ("reports/html.py", "from nodes.ros import common", "reports.html -> nodes.ros"),
        ("nodes/recording/layout.py", "import netem.traces", "nodes.recording.layout -> netem"),
        ("netem/nr/phy.py", "import netem.relay", "netem.nr.phy -> netem.relay"),
        (
            "netem/stages/pipeline.py",
            "from netem.nr.ue import Slots",
            "netem.stages.pipeline -> netem.nr.ue",
        ),
        ("netem/tc/plan.py", "from netem.gtpu import wire", "netem.tc.plan -> netem.gtpu.wire"),
        ("netem/gso.py", "import netem.stages", "netem.gso -> netem.stages"),
        ("netem/directions.py", "import netem.profile", "netem.directions -> netem.profile"),
    ],
    ids=[
        "up-two-layers",
        "type-checking-only",
        "middle-to-top",
        "across-a-layer",
        "sideways",
        "nr-phy-to-relay",
        "pipeline-to-the-ue-stage",
        "tc-to-gtpu",
        "foundation-to-a-wing",
        "the-words-to-a-wing",
    ],
)
def test_an_upward_or_sideways_import_breaks_the_check(
    tmp_path: Path, module: str, added: str, says: str
) -> None:
    root = _copy_tree(tmp_path)
    path = root / module
    path.write_text(path.read_text() + "\n" + added + "  # noqa\n")
    out = _lint(root)
    assert out.returncode != 0, out.stdout
    assert "BROKEN" in out.stdout and says in out.stdout, out.stdout


def _module_graph() -> dict[str, set[str]]:
    """Module -> first-party modules it imports (any import, TYPE_CHECKING ones included;
    `from pkg import sub` counts as importing `pkg.sub`, not the package)."""
    import ast

    modules: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts)
            modules[name.removesuffix(".__init__")] = path
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                subs = {f"{node.module}.{a.name}" for a in node.names} & modules.keys()
                graph[name] |= subs
                if node.module in modules and len(subs) < len(node.names):
                    graph[name].add(node.module)
            elif isinstance(node, ast.Import):
                graph[name] |= {a.name for a in node.names} & modules.keys()
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_module_imports_itself_back() -> None:
    """No cycles between modules: the namespace and link mechanics declare what they need of
    the topology (protocols) instead of importing it."""
    graph = _module_graph()
    assert "testbed.links" in graph["testbed.topology.build"]  # the graph is the real one
    assert _cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]


def package_graph() -> dict[tuple[str, str], int]:
    """(importing package, imported package) -> how many module-level imports cross that way,
    packages as the layers name them (nodes.edgeloc, nodes.ros, nodes.recording, ...)."""

    def package(module: str) -> str:
        parts = module.split(".")
        return ".".join(parts[:2]) if parts[0] == "nodes" and len(parts) > 1 else parts[0]

    counts: dict[tuple[str, str], int] = {}
    for module, imported in _module_graph().items():
        for other in imported:
            edge = (package(module), package(other))
            if edge[0] != edge[1]:
                counts[edge] = counts.get(edge, 0) + 1
    return counts


if __name__ == "__main__":  # python -m tests.test_layers: the import graph between packages
    for (a, b), n in sorted(package_graph().items()):
        print(f"{a} -> {b}: {n}")
    print(f"module cycles: {_cycles(_module_graph()) or 'none'}")


def test_no_module_of_the_product_is_over_800_lines() -> None:
    """One module, one reason to change: a module that grows past 800 lines is split, not
    waved through (the tests are not the product and may be longer)."""
    modules = [
        p
        for package in ("testbed", "netem", "nodes", "reports")
        for p in (REPO / package).rglob("*.py")
        if "__pycache__" not in p.parts
    ]
    assert len(modules) > 150, modules  # the check must be looking at the tree
    long = {str(p.relative_to(REPO)): n for p in modules if (n := p.read_text().count("\n")) > 800}
    assert not long, f"modules over 800 lines: {long}"
