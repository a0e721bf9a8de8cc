"""How the house is laid out, in figures: the longest modules and functions of the product, and
the imports between its subpackages. Run from the repository root, before and after a move:

    .venv/bin/python tests/house.py            # sizes
    .venv/bin/python tests/house.py --graph    # and the import graph between subpackages

Reads the files git tracks (and untracked ones it does not ignore) under testbed/, netem/,
nodes/ and reports/; runs nothing of them. The layer rules themselves are `make lint`'s.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
from collections import Counter
from pathlib import Path

PACKAGES = ("testbed", "netem", "nodes", "reports")


def product_files() -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "*.py"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    return sorted({f for f in listed if f.split("/", 1)[0] in PACKAGES and Path(f).exists()})


def module_name(path: str) -> str:
    name = path[:-3].replace("/", ".")
    return name.removesuffix(".__init__")


def unit(module: str, depth: int) -> str:
    return ".".join(module.split(".")[:depth])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--graph", action="store_true", help="print the import graph too")
    parser.add_argument("--depth", type=int, default=2, help="package depth of a graph node")
    parser.add_argument("--most", type=int, default=12, help="rows of each longest list")
    args = parser.parse_args()
    modules: list[tuple[int, str]] = []
    bodies: list[tuple[int, str]] = []
    edges: Counter[tuple[str, str]] = Counter()
    for path in product_files():
        source = Path(path).read_text()
        modules.append((source.count("\n"), path))
        here = unit(module_name(path), args.depth)
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                kind = "class" if isinstance(node, ast.ClassDef) else "def"
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                bodies.append((length, f"{path}:{node.name} ({kind})"))
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            for target in targets:
                there = unit(target, args.depth)
                if target.split(".")[0] in PACKAGES and there != here:
                    edges[here, there] += 1
    modules.sort(reverse=True)
    bodies.sort(reverse=True)
    over = sum(1 for n, _ in modules if n > 800)
    print(f"modules: {len(modules)}, lines: {sum(n for n, _ in modules)}, over 800: {over}")
    print("longest modules:")
    for n, path in modules[: args.most]:
        print(f"  {n:5d} {path}")
    print("longest functions/classes:")
    for n, name in bodies[: args.most]:
        print(f"  {n:5d} {name}")
    if args.graph:
        print(f"import graph (depth {args.depth}; edges counted in import statements):")
        for (a, b), count in sorted(edges.items()):
            print(f"  {a} -> {b} ({count})")


if __name__ == "__main__":
    main()
