"""A real (short) run ends with its report, and `testbed report` rebuilds the same summary.json
from run.mcap alone, anywhere.

Runs the real `testbed` executable on the smoke scenario shortened to 4 s, with every report
format and the figures on, in a private state directory (EDGELOC_STATE_DIR)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from tests.realrun import testbed_cli

pytestmark = [pytest.mark.root, pytest.mark.ros, pytest.mark.e2e, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]


def test_run_reports_and_the_report_rebuilds_identically(state_dir: Path, tmp_path: Path) -> None:
    text = (REPO / "scenarios/smoke.yaml").read_text()
    text = text.replace("duration: 20s", "duration: 4s").replace("at: 10s", "at: 2s")
    text, n = re.subn(
        r"(?m)^report:.*$",
        "report: {enabled: true, formats: [html, md, json], plots: true, link_test: false}",
        text,
    )
    assert n == 1, "scenarios/smoke.yaml has no one-line `report:` to override"
    short = tmp_path / "smoke-report.yaml"
    short.write_text(text)
    runs = tmp_path / "runs"

    result = testbed_cli("run", str(short), "--runs-dir", str(runs))
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (folder,) = runs.iterdir()
    *_, headline, where = result.stdout.strip().splitlines()
    assert headline.startswith(f"run {folder.name}: EdgeLoc total error "), result.stdout[-2000:]
    report_line = rf"report: {re.escape(str(folder / 'report.html'))}, built in [0-9.]+ s"
    assert re.fullmatch(report_line, where), where

    summary = json.loads((folder / "summary.json").read_text())
    assert summary["status"] == "ok" and summary["partial"] is False
    assert summary["headline"] == headline
    for method in ("vo", "dnn", "kalman", "edgeloc"):
        assert summary["methods"][method]["frames"] > 0, method
    assert summary["links"]["backend"], "the report must say which link backend ran"
    html = (folder / "report.html").read_text()
    assert html.count('src="data:image/png;base64,') >= 6
    # Issue #14: the report of a real run compares the learned split with each fixed split
    # and the oracle, replayed under the latencies this run measured, and draws error
    # against latency per split
    splits = summary["splits"]
    assert splits["latency_source"] == "measured", splits.get("skipped")
    policies = [r["policy"] for r in splits["rows"]]
    assert policies[0] == "learned" and "oracle" in policies
    assert {f"fixed:{k}" for k in splits["replayed_splits"]} <= set(policies)
    md = (folder / "report.md").read_text()
    assert "## Split points: learned, fixed, oracle" in md
    assert (folder / "plots" / "split_error_latency.png").is_file()

    # Rebuilt elsewhere from the MCAP alone: the same bytes.
    again = tmp_path / "again"
    again.mkdir()
    shutil.copyfile(folder / "run.mcap", again / "run.mcap")
    rebuilt = testbed_cli("report", str(again), "--formats", "json,md")
    assert rebuilt.returncode == 0, rebuilt.stdout + rebuilt.stderr
    assert (again / "summary.json").read_bytes() == (folder / "summary.json").read_bytes()
    # run.json rides in run.mcap, so what only it holds (here the path to the edge) is there
    # too: the same report.md, word for word
    from mcap.reader import make_reader

    with open(again / "run.mcap", "rb") as f:
        attached = {a.name: a.data for a in make_reader(f).iter_attachments()}
    assert json.loads(attached["run.json"]) == json.loads((folder / "run.json").read_text())
    assert "## Path to the edge" in (folder / "report.md").read_text()
    assert (again / "report.md").read_text() == (folder / "report.md").read_text()
