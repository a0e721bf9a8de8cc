"""`testbed fidelity`: the emulated cell against published measurements of real 5G systems
(the work is in `testbed.fidelity`)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from testbed import console as con
from testbed.cli.common import EXIT_FAILED, KNOWN_ERRORS, JsonFlag, fail


def fidelity(
    cases: Annotated[
        list[str] | None,
        typer.Argument(
            help="Cases of scenarios/fidelity by name (default: every one).",
            show_default=False,
            metavar="[CASE]...",
        ),
    ] = None,
    out: Annotated[
        Path,
        typer.Option("--out", help="Where fidelity.json and the CDF figures go.", file_okay=False),
    ] = Path("runs/fidelity"),
    count: Annotated[
        int | None,
        typer.Option(
            "--count", min=50, help="Probes per variant and measure (default: the case's)."
        ),
    ] = None,
    model: Annotated[
        bool,
        typer.Option(
            "--model",
            help="The link's stages on a fake clock instead of packets through the relay "
            "(no root; seconds).",
        ),
    ] = False,
    json_out: JsonFlag = False,
) -> None:
    """Run each case's probe through the relay in namespaces (real packets) and print ours
    against theirs: min / p50 / mean / p90 / p99 per direction (and round trip), the
    components the source gives (HARQ share and step, segmented share), W1 and KS against the
    source's own samples, floors, and a verdict per case. Writes fidelity.json and one CDF
    figure per case to --out. Exits 1 if any case is out of tolerance.

    Tolerances: medians within 10% or 0.5 ms, p90/p95/p99 within 20% or 1 ms, means within
    10%; W1 within the source data's own sampling spread for as many probes, plus 0.3 ms of
    host. Examples: testbed fidelity; testbed fidelity srsran-urllc --count 300
    """
    from testbed.fidelity import find, run_cases, table, to_dict, write
    from testbed.fidelity.case import shortened

    progress = None if json_out else con.plain
    try:
        chosen = find(list(cases or []))
        if count is not None:
            chosen = [shortened(c, count) for c in chosen]
        results = run_cases(chosen, real=not model, progress=progress)
        paths = write(results, out)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    ok = all(r.ok for r in results)
    if json_out:
        sys.stdout.write(json.dumps(to_dict(results), indent=2) + "\n")
    else:
        for line in table(results).splitlines():
            con.plain(line)
        con.plain(f"wrote {', '.join(str(p) for p in paths)}")
    if not ok:
        if not json_out:
            bad = ", ".join(r.case.name for r in results if not r.ok)
            con.error(f"out of tolerance: {bad} (rows marked OUT)")
        raise typer.Exit(EXIT_FAILED)
    if not json_out:
        con.ok(f"every case within tolerance ({len(results)} case(s))")
