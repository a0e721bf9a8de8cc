"""The run itself: its metadata and outcome, the nodes that did not exit cleanly, the node
processes, and the recording (topics, what was not recorded, attachments, packet captures).

Its keys of summary.json:

- `run`: the recorder's `edgeloc.run` metadata as recorded (run_id, scenario, seed,
  link_backend, status, started, ended, duration_s, software versions, host capabilities);
- `partial` (bool) and `recording`: {file, complete (footer read, no damage), problems [text],
  messages (per topic), schemas (per topic), decode_errors}. `partial` is true when the file
  was cut short or the run was interrupted: every figure then covers only what was recorded;
- `status`: the run's status ("ok", "failed: ...", "interrupted", or "unknown ...");
- `nodes`: the recorder's `edgeloc.nodes` metadata as recorded; `failures`: [{process,
  exit_code, namespace, last_log_lines}] for processes that exited non-zero or carry log
  lines of a failure;
- `not_recorded`: topics/records the report looked for and did not find (`/handover` only
  where `channel.handover` was set and a serving cell changed on /radio).
"""

from __future__ import annotations

from typing import Any

from netem.directions import DIRECTIONS
from nodes.recording.layout import HANDOVER_TOPIC, PCAP_DIR
from reports.document import Code, Para, Section, Table
from reports.mcapread import RunData
from reports.sections.fmt import cell, not_recorded_note
from reports.sections.radio import handovers_unrecorded


def recording_summary(data: RunData) -> dict[str, Any]:
    """summary.json's `recording`: what the file held, and what of it could not be read."""
    return {
        "file": data.path.name,
        "complete": data.complete,
        "problems": data.problems,
        "messages": data.topics,
        "schemas": data.schemas,
        "decode_errors": data.decode_errors,
    }


#: Keys under which the recorder may put a process's last log lines.
LOG_KEYS = ("last_log_lines", "log_tail", "last_log", "log_lines")


def last_log_lines(info: dict[str, Any]) -> list[str]:
    for k in LOG_KEYS:
        v = info.get(k)
        if isinstance(v, str):
            return v.splitlines()
        if isinstance(v, list):
            return [str(x) for x in v]
    return []


def exit_code_of(info: dict[str, Any]) -> int | None:
    for k in ("exit_code", "exit", "returncode"):
        v = info.get(k)
        if isinstance(v, int) and not isinstance(v, bool):
            return v
    return None


def failures(data: RunData) -> list[dict[str, Any]]:
    out = []
    for proc, info in sorted((data.nodes or {}).items()):
        if not isinstance(info, dict):
            continue
        code, lines = exit_code_of(info), last_log_lines(info)
        if (code is not None and code != 0) or lines:
            out.append(
                {
                    "process": proc,
                    "namespace": info.get("namespace"),
                    "exit_code": code,
                    "last_log_lines": lines,
                }
            )
    return out


def topics_of(data: RunData, vehicle: str) -> set[str]:
    prefix = f"/{vehicle}/"
    return {t[len(prefix) :] for t in data.topics if t.startswith(prefix)}


def not_recorded(data: RunData) -> list[str]:
    missing = []
    if not data.run:
        missing.append("metadata edgeloc.run")
    if not data.nodes:
        missing.append("metadata edgeloc.nodes")
    if not data.linktest:
        ran = str(data.linktest_meta.get("ran", "")).lower()
        why = "it did not run (report.link_test off)" if ran == "false" else "no linktest.json"
        missing.append(f"link self-test table: {why}")
    if not data.vehicles:
        missing.append("any vehicle topic (/<vehicle>/gt, /pose, ...)")
    for v in data.vehicles:
        have = topics_of(data, v)
        missing += [f"/{v}/{t}" for t in VEHICLE_TOPICS_REQUIRED if t not in have]
    if not data.link_events:
        missing.append("/links/events")
    if not data.counters:
        missing.append("/links/counters")
    if handovers_unrecorded(data):
        missing.append(HANDOVER_TOPIC)
    return missing


VEHICLE_TOPICS_REQUIRED = ("gt", "pose", "dnn_answer", "split_decision", "detector", "inference")


def overview_section(data: RunData, s: dict[str, Any]) -> Section:
    sec = Section("Run")
    if s["partial"]:
        why = "; ".join(data.problems) or f"the run ended with status {s['status']!r}"
        sec.add(
            Para(
                f"PARTIAL REPORT: the recording does not cover the whole run ({why}). Every "
                "figure below covers only what was recorded.",
                "warning",
            )
        )
    if str(s["status"]).startswith("failed"):
        why = str(s["status"]).removeprefix("failed").lstrip(": ") or "no reason recorded"
        sec.add(Para(f"The run FAILED: {why}", "warning"))
    run = s["run"]
    keys = ["run_id", "scenario", "seed", "status", "link_backend", "started", "ended"]
    keys += ["duration_s", "testbed_version", "python", "ros", "torch", "kernel"]
    rows = [[k, cell(run.get(k), "{:g}")] for k in keys if k in run]
    rows += [
        [k, cell(v, "{:g}")]
        for k, v in run.items()
        if k not in keys and not isinstance(v, dict | list)
    ]
    if rows:
        sec.add(Table(["field", "value"], rows))
    else:
        sec.add(not_recorded_note("the run's metadata (edgeloc.run)"))
    backend = run.get("link_backend")
    sec.add(Para(f"Link backend that ran: {backend}" if backend else "Link backend: not recorded."))
    for k, v in run.items():
        if isinstance(v, dict | list) and v:
            rows = [[str(a), cell(b, "{:g}")] for a, b in v.items()] if isinstance(v, dict) else []
            if rows:
                sec.add(Table([k, "value"], rows, caption=k.replace("_", " ")))
            else:
                sec.add(Code("\n".join(str(x) for x in v), caption=k))
    return sec


def failures_section(s: dict[str, Any]) -> Section | None:
    if not s["failures"]:
        return None
    # In a run that ended "ok", a non-zero exit is a node that had to be killed at the stop.
    ok = s["status"] == "ok"
    sec = Section("Nodes that did not exit cleanly" if ok else "Failed nodes")
    for f in s["failures"]:
        sec.add(
            Para(
                f"{f['process']} (namespace {f['namespace'] or '-'}) "
                + (
                    "has no exit code recorded"
                    if f["exit_code"] is None
                    else f"exited with code {f['exit_code']}"
                )
                + ".",
                "warning",
            )
        )
        if f["last_log_lines"]:
            sec.add(
                Code("\n".join(f["last_log_lines"]), caption=f"last log lines of {f['process']}")
            )
        else:
            sec.add(not_recorded_note(f"the log lines of {f['process']}"))
    return sec


def nodes_section(s: dict[str, Any]) -> Section:
    sec = Section("Nodes")
    nodes = s["nodes"]
    if not nodes:
        return sec.add(not_recorded_note("node processes", "metadata edgeloc.nodes"))
    rows = []
    for proc, info in nodes.items():
        info = info if isinstance(info, dict) else {}
        stats = info.get("stats") if isinstance(info.get("stats"), dict) else {}
        brief = ", ".join(
            f"{k}={cell(v, '{:.4g}') if isinstance(v, float) else v}"
            for k, v in stats.items()
            if isinstance(v, int | float | str) and k != "node"
        )
        rows.append([proc, str(info.get("namespace", "-")), cell(exit_code_of(info), "{}"), brief])
    return sec.add(Table(["process", "namespace", "exit code", "stats"], rows))


#: What a report cannot show without the run's run.json (a run that ended before writing it).
NO_RUN_JSON = (
    "No run.json, in the run folder or attached to run.mcap (the run ended before writing "
    "it): the path to the edge, apps, cross-traffic and EdgeLoc under load are left out."
)


def recording_section(data: RunData, s: dict[str, Any]) -> Section:
    sec = Section("Recording")
    rec = s["recording"]
    sec.add(
        Para(
            f"{rec['file']}: {'complete' if rec['complete'] else 'INCOMPLETE'}, "
            f"{sum(rec['messages'].values())} messages decoded, {rec['decode_errors']} not."
        )
    )
    for p in rec["problems"]:
        sec.add(Para(p, "warning"))
    sec.add(
        Table(
            ["topic", "type", "messages"],
            [[t, rec["schemas"].get(t, "-"), str(n)] for t, n in rec["messages"].items()],
        )
    )
    if s["not_recorded"]:
        sec.add(Para("Not recorded: " + ", ".join(s["not_recorded"]) + ".", "note"))
    if data.attachments:
        sec.add(Para("Attachments: " + ", ".join(sorted(data.attachments)) + "."))
    if not data.run_json:
        sec.add(Para(NO_RUN_JSON, "note"))
    _captures(sec, data)
    return sec


def _captures(sec: Section, data: RunData) -> None:
    """The run's packet captures (`record.pcap`) beside run.mcap, with what run.json says each
    holds."""
    files = sorted((data.path.parent / PCAP_DIR).glob("*.pcapng"))
    if not files:
        return
    captures = data.run_json.get("captures") or {}
    rows = []
    for f in files:
        info = captures.get(f.stem) or {}
        packets, dropped = info.get("packets") or {}, info.get("dropped") or {}
        rows.append(
            [
                f"{PCAP_DIR}/{f.name}",
                f"{f.stat().st_size / 1e6:.2f}",
                *[f"{packets.get(d, '-')} / {dropped.get(d, '-')}" for d in DIRECTIONS],
            ]
        )
    sec.add(
        Table(
            ["capture (open in Wireshark)", "MB", "uplink packets / dropped", "downlink"],
            rows,
            caption="what each link delivered, after its impairments; drops are counted, "
            "not captured",
            link_columns=(0,),
        )
    )
