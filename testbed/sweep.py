"""`testbed sweep`: one scenario, a grid of variants, one comparison report across them.

A variant is the scenario file with some fields replaced (`--set KEY=V1,V2,...`, one axis per
option; the grid is every combination). Overrides are made on the YAML tree, before any checking,
and each variant is then checked by the scenario loader itself: a value is valid in a sweep
exactly when it would be valid written in the file, and a wrong one is reported the way
`testbed validate` reports it (field path, expected, found), naming the `--set` that made it.

Keys are dotted paths into the YAML, as an author reads it:

- mapping keys: `workload.learner.window`, `links.air.uplink.delay`, `duration`, `seed`;
- list items by index or by name: `timeline[1].uplink`, `topology.vehicles[0].cpu`,
  `topology.vehicles.av2.cpu` (an item whose `name`, `gnb` or `link` is that word);
- one link alone: `links.av1-gnb1.uplink.delay` becomes (or changes) that link's entry in
  `links.overrides`, so the other links keep the `links.air` / `links.backhaul` defaults.

Values are YAML scalars as in the file (`8ms`, `20mbit`, `0.5%`, `30`, `true`, `null`) or a flow
list in brackets (`[image,conv3]`: commas inside brackets do not separate values).

Each variant runs with the offline replay (`testbed replay`'s engine, every vehicle of the
scenario, DNN outputs shared between variants that drive the same frames) or, with `real=True`,
as a real run (`testbed run`: namespaces, links, ROS 2 nodes). The report is `sweep.json`,
`sweep.md` (one table) and `sweep.png` (errors and latency across the variants).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import itertools
import json
import math
import re
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from netem.errors import NetemError
from nodes.recording import RecordingError
from nodes.recording import layout as names
from testbed.errors import BadInput, HostError, TestbedError
from testbed.scenario.issues import Issue, ScenarioError
from testbed.scenario.model import Scenario
from testbed.scenario.schema_v1 import LINK_NAME_PATTERN

Progress = Callable[[str], None]

METHODS = ("vo", "dnn", "kalman", "edgeloc")
#: Keys of `links` that are not link names (a `links.<word>` path with another word is a link).
_LINKS_KEYS = ("backend", "air", "backhaul", "overrides")
#: Keys that name a list item, tried in this order (`topology.vehicles.av2` = the item named av2).
_ITEM_NAME_KEYS = ("name", "gnb", "link")
_SEGMENT = re.compile(r"^(?P<key>[^\[\]]+)?(?P<index>(\[\d+\])*)$")
#: A grid larger than this is almost surely a typo (and would run for hours).
MAX_VARIANTS = 64


# ---- axes and the grid ----------------------------------------------------------------------


@dataclass(frozen=True)
class Axis:
    """One `--set KEY=V1,V2,...`: a field and the values it takes (as written, and parsed)."""

    key: str
    texts: tuple[str, ...]
    values: tuple[Any, ...]


def split_values(text: str) -> list[str]:
    """`a,b,[c,d]` -> ['a', 'b', '[c,d]']: commas split values except inside brackets."""
    out: list[str] = []
    depth, start = 0, 0
    for i, ch in enumerate(text):
        if ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i].strip())
            start = i + 1
    out.append(text[start:].strip())
    return out


def parse_value(text: str, option: str) -> Any:
    """A value as YAML would read it in the file (`8ms` stays a string, `30` is a number)."""
    if text == "":
        raise BadInput(f"--set {option}: an empty value (write null to unset a field)")
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as err:
        first = str(err).splitlines()[0]
        raise BadInput(f"--set {option}: {text!r} is not a YAML value ({first})") from None
    return value


def parse_set(option: str) -> Axis:
    """`KEY=V1,V2,...` -> an `Axis`; raises `BadInput` (exit 2) naming what is wrong."""
    key, eq, rest = option.partition("=")
    key = key.strip()
    if not eq or not key:
        raise BadInput(
            f"--set {option!r}: expected KEY=V1,V2,... (e.g. links.air.uplink.delay=4ms,20ms)"
        )
    path_segments(key)  # a malformed path fails here, before anything runs
    texts = split_values(rest)
    values = tuple(parse_value(t, f"{key}={rest}") for t in texts)
    if len(set(texts)) != len(texts):
        raise BadInput(f"--set {key}: a value is listed twice ({rest})")
    return Axis(key, tuple(texts), values)


def grid(axes: Sequence[Axis]) -> list[dict[str, Any]]:
    """Every combination of the axes' values, the first axis varying slowest; each variant is
    {key: value}. Raises `BadInput` for a key set twice or a grid over `MAX_VARIANTS`."""
    keys = [a.key for a in axes]
    if len(set(keys)) != len(keys):
        twice = next(k for k in keys if keys.count(k) > 1)
        raise BadInput(f"--set {twice} is given twice; put all its values in one option")
    size = math.prod(len(a.values) for a in axes) if axes else 0
    if not axes:
        raise BadInput("nothing to sweep: give at least one --set KEY=V1,V2,...")
    if size > MAX_VARIANTS:
        raise BadInput(
            f"the grid has {size} variants (more than {MAX_VARIANTS}); sweep fewer values"
        )
    return [
        dict(zip(keys, combo, strict=True))
        for combo in itertools.product(*(a.values for a in axes))
    ]


def label(axes: Sequence[Axis], variant_index: int) -> dict[str, str]:
    """The values of variant `variant_index` as written on the command line."""
    combos = list(itertools.product(*(a.texts for a in axes)))
    return dict(zip([a.key for a in axes], combos[variant_index], strict=True))


# ---- overrides on the YAML tree -------------------------------------------------------------


def path_segments(key: str) -> list[str | int]:
    """`timeline[1].uplink` -> ['timeline', 1, 'uplink']; raises `BadInput` when malformed."""
    out: list[str | int] = []
    for part in key.split("."):
        m = _SEGMENT.match(part)
        if not part or m is None or (m["key"] is None and not m["index"]):
            raise BadInput(
                f"--set {key}: {part!r} is not a key; expected dotted keys with optional "
                "[index], like workload.learner.window or timeline[0].uplink"
            )
        if m["key"] is not None:
            out.append(m["key"])
        out += [int(i) for i in re.findall(r"\[(\d+)\]", m["index"])]
    return out


def _item_by_name(items: list[Any], word: str) -> Any | None:
    for it in items:
        if isinstance(it, dict) and any(it.get(k) == word for k in _ITEM_NAME_KEYS):
            return it
    return None


def set_path(data: dict[str, Any], key: str, value: Any) -> None:
    """Set `key` (a dotted path, see the module doc) to `value` in the YAML tree `data`.

    Missing mappings on the way are created (`workload.learner.window` works when the file has
    no `learner:`); a missing list item is an error. Whether the key is a field of the scenario
    is the loader's call, which says "unknown key, did you mean ...".
    """
    segments = path_segments(key)
    if (
        len(segments) >= 2
        and segments[0] == "links"
        and isinstance(segments[1], str)
        and segments[1] not in _LINKS_KEYS
        and re.fullmatch(LINK_NAME_PATTERN, segments[1])
    ):
        # links.<link>.<...>: that link's entry in links.overrides (made when missing).
        links = data.setdefault("links", {})
        if not isinstance(links, dict):
            raise BadInput(f"--set {key}: links is not a mapping in the scenario file")
        overrides = links.setdefault("overrides", [])
        if not isinstance(overrides, list):
            raise BadInput(f"--set {key}: links.overrides is not a list in the scenario file")
        entry = next(
            (o for o in overrides if isinstance(o, dict) and o.get("link") == segments[1]), None
        )
        if entry is None:
            entry = {"link": segments[1]}
            overrides.append(entry)
        if len(segments) == 2:
            raise BadInput(f"--set {key}: name a direction and a field, like {key}.uplink.delay")
        segments = ["links", "overrides", overrides.index(entry), *segments[2:]]
    node: Any = data
    walked: list[str] = []
    for i, seg in enumerate(segments):
        last = i == len(segments) - 1
        where = _shown(walked) or "the top level"
        if isinstance(seg, int):
            if not isinstance(node, list):
                raise BadInput(f"--set {key}: {where} is not a list, so [{seg}] names nothing")
            if seg >= len(node):
                raise BadInput(
                    f"--set {key}: {where} has {len(node)} item(s); [{seg}] is not one of them"
                )
            if last:
                node[seg] = value
            else:
                node = node[seg]
            walked.append(f"[{seg}]")
            continue
        if isinstance(node, list):
            item = _item_by_name(node, seg)
            if item is None:
                names = [
                    str(next(it[k] for k in _ITEM_NAME_KEYS if k in it))
                    for it in node
                    if isinstance(it, dict) and any(k in it for k in _ITEM_NAME_KEYS)
                ]
                raise BadInput(
                    f"--set {key}: {where} has no item named {seg!r} "
                    f"(items: {', '.join(names) or 'none'}); use an index like [0]"
                )
            if last:
                raise BadInput(f"--set {key}: name a field of {where}.{seg}, like {key}.cpu")
            node = item
            walked.append(f".{seg}")
            continue
        if not isinstance(node, dict):
            raise BadInput(f"--set {key}: {where} is a value, not a mapping with keys")
        if last:
            node[seg] = value
        else:
            nxt = node.get(seg)
            if nxt is None:
                nxt = node[seg] = {}
            node = nxt
        walked.append(f".{seg}")


def _shown(walked: list[str]) -> str:
    return "".join(walked).lstrip(".")


def read_tree(file: Path) -> dict[str, Any]:
    """The scenario file as a plain YAML tree (checked first, so a sweep of a broken file
    reports the file's own errors with their lines)."""
    from testbed.scenario import load

    load(file)  # raises ScenarioError with file:line:column
    data = yaml.safe_load(file.read_text(encoding="utf-8"))
    if not isinstance(data, dict):
        raise BadInput(f"{file}: the scenario is not a mapping")
    return data


def variant_tree(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    data = copy.deepcopy(base)
    for key, value in overrides.items():
        set_path(data, key, value)
    return data


def load_tree(data: dict[str, Any], file: Path, what: str) -> Scenario:
    """Check a (modified) YAML tree with the scenario loader, paths relative to `file`.

    Issues in the tree are reported against `what` (the `--set` options), by field path: the
    tree has no lines of its own. Issues in other files (a trace) keep their location.
    """
    from testbed.scenario import loads

    source = f"<{file} with {what}>"
    text = yaml.safe_dump(data, sort_keys=False)
    try:
        scenario = loads(text, source=source, base_dir=file.parent)
    except ScenarioError as err:
        issues = [
            Issue(f"{file} with {what}", None, None, i.path, i.expected, i.found, i.hint)
            if i.file == source
            else i
            for i in err.issues
        ]
        raise ScenarioError(issues) from None
    return scenario


def shorten(data: dict[str, Any], duration_s: float) -> dict[str, Any]:
    """A copy of a scenario tree cut to `duration_s`, its timeline scaled with it (event times
    and outage lengths), so every phase of a long scenario is still played, briefly. Traces
    play at their own pace: a shortened trace-driven run sees the start of its trace."""
    from testbed import units

    out = copy.deepcopy(data)
    full = units.parse_duration(str(data["duration"]))
    factor = min(1.0, duration_s / full)
    out["duration"] = f"{duration_s:g}s"
    for event in out.get("timeline") or []:
        if not isinstance(event, dict):
            continue
        for k in ("at", "for"):
            if k in event:
                scaled = units.parse_duration(str(event[k])) * factor
                event[k] = f"{round(scaled, 3):g}s" if scaled else 0
    return out


# ---- running the grid -----------------------------------------------------------------------


@dataclass
class VariantResult:
    """One row of the report: a variant on one vehicle."""

    index: int
    values: dict[str, str]
    vehicle: str
    folder: str
    methods: dict[str, dict[str, float | None]]  # method -> {total_m, mean_m}
    reductions_pct: dict[str, float | None]  # EdgeLoc's reduction vs vo, dnn, kalman
    split_share: dict[str, float]
    mean_latency_s: float | None  # answered requests, thread 2 start -> answer
    requests: int
    lost: int
    wall_s: float
    error: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class SweepReport:
    scenario: str
    mode: str  # replay | real
    axes: list[Axis]
    rows: list[VariantResult] = field(default_factory=list)
    out: Path = Path()
    wall_s: float = 0.0

    @property
    def failed(self) -> list[VariantResult]:
        return [r for r in self.rows if r.error]

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "mode": self.mode,
            "axes": [{"key": a.key, "values": list(a.texts)} for a in self.axes],
            "variants": [r.to_dict() for r in self.rows],
            "wall_s": round(self.wall_s, 3),
            "notes": _notes(self.mode),
        }


def _notes(mode: str) -> list[str]:
    if mode == "replay":
        return [
            "offline replay: the EdgeLoc loop in one process with a latency model of the path",
            "each vehicle is replayed on its own path; vehicles sharing a hop do not slow each "
            "other down in the replay (a real run, --real, has them contend)",
            "reductions: (baseline total - EdgeLoc total) / baseline total, as the paper's",
        ]
    return [
        "real runs: namespaces, emulated links and ROS 2 nodes (testbed run) per variant",
        "errors over the frames the fusion node scored; latency from the inference node",
        "reductions: (baseline total - EdgeLoc total) / baseline total, as the paper's",
    ]


def _reductions(methods: dict[str, dict[str, float | None]]) -> dict[str, float | None]:
    edge = methods["edgeloc"]["total_m"]
    out: dict[str, float | None] = {}
    for m in ("vo", "dnn", "kalman"):
        base = methods[m]["total_m"]
        out[m] = None if edge is None or not base else 100.0 * (base - edge) / base
    return out


class _ReplayEngine:
    """Replays variants; datasets, the model and DNN outputs are shared between variants that
    drive the same frames (the DNN is the slow part, and its answers do not depend on the
    network)."""

    def __init__(self) -> None:
        self.datasets: dict[tuple[Any, ...], Any] = {}
        self.models: dict[str | None, Any] = {}
        self.caches: dict[tuple[Any, ...], Any] = {}

    def run(
        self, scenario: Scenario, folder: Path, index: int, values: dict[str, str]
    ) -> list[VariantResult]:
        from nodes.edgeloc.dataset import open_dataset
        from nodes.edgeloc.replay import InferenceCache, run_replay
        from nodes.edgeloc.train import load_model
        from testbed.replay import latency_model, replay_config

        cfg = replay_config(scenario)
        dkey = (cfg.dataset, cfg.seed, cfg.rate_hz, cfg.duration_s, cfg.corruption)
        if dkey not in self.datasets:
            self.datasets[dkey] = open_dataset(
                cfg.dataset,
                seed=cfg.seed,
                rate_hz=cfg.rate_hz,
                duration_s=cfg.duration_s,
                corruption=cfg.corruption,
            )
        if cfg.weights not in self.models:
            self.models[cfg.weights] = load_model(cfg.weights)
        ckey = (*dkey, cfg.weights, cfg.codec)
        if ckey not in self.caches:
            self.caches[ckey] = InferenceCache(
                self.models[cfg.weights], self.datasets[dkey], cfg.codec
            )
        rows = []
        for v in scenario.topology.vehicles:
            model = latency_model(scenario, vehicle=v.name)
            try:
                result = run_replay(
                    cfg, model, self.datasets[dkey], self.models[cfg.weights], self.caches[ckey]
                )
            except ValueError as err:  # a recorded dataset or weights that do not fit
                raise BadInput(f"{scenario.name}: {err}") from None
            where = folder / v.name
            summary = result.write(where)
            methods = {
                m: {
                    "total_m": summary["methods"][m]["position_m"]["total"],  # type: ignore[index]
                    "mean_m": summary["methods"][m]["position_m"]["mean"],  # type: ignore[index]
                }
                for m in METHODS
            }
            ok = [p.latency_s for p in result.plays if not p.lost]
            rows.append(
                VariantResult(
                    index=index,
                    values=values,
                    vehicle=v.name,
                    folder=str(where),
                    methods=methods,
                    reductions_pct=_reductions(methods),
                    split_share=dict(summary["learner"]["split_share"]),  # type: ignore[index]
                    mean_latency_s=sum(ok) / len(ok) if ok else None,
                    requests=len(result.plays),
                    lost=sum(p.lost for p in result.plays),
                    wall_s=result.wall_s,
                )
            )
        return rows


def _real_rows(
    scenario: Scenario, runs_dir: Path, index: int, values: dict[str, str], progress: Progress
) -> list[VariantResult]:
    from testbed.run import run_scenario

    t0 = time.perf_counter()
    result = run_scenario(scenario, runs_dir, progress=lambda line: progress(f"    {line}"))
    wall = time.perf_counter() - t0
    procs = result.nodes.get("processes", {}) if isinstance(result.nodes, dict) else {}
    recorded = _report_summary(scenario, result.folder, progress)
    rows = []
    for v in scenario.topology.vehicles:
        fusion = procs.get(f"{v.name}.fusion", {}).get("stats", {})
        inference = procs.get(f"{v.name}.inference", {}).get("stats", {})
        errors = fusion.get("errors", {})
        methods = {
            m: {
                "total_m": errors.get(m, {}).get("total_m"),
                "mean_m": errors.get(m, {}).get("mean_m"),
            }
            for m in METHODS
        }
        # The run's report (summary.json, built from run.mcap like `testbed run` does) scores
        # every frame that was recorded: the better source when it is there.
        block = (recorded or {}).get("per_vehicle", {}).get(v.name, {}).get("methods", {})
        with contextlib.suppress(KeyError, TypeError):
            methods = {
                m: {
                    "total_m": block[m]["position_m"]["total"],
                    "mean_m": block[m]["position_m"]["mean"],
                }
                for m in METHODS
            }
        plays = inference.get("split_plays", {})
        n = sum(plays.values())
        lat = inference.get("mean_latency_s", {})
        weighted = [(plays.get(k, 0), s) for k, s in lat.items() if s is not None]
        answered = sum(c for c, _ in weighted)
        error = None
        if not result.ok:
            error = "a vehicle could not reach its edge server (see connectivity.json)"
        elif not fusion:
            error = f"no statistics from {v.name}'s nodes ({result.nodes.get('skipped', '')})"
        rows.append(
            VariantResult(
                index=index,
                values=values,
                vehicle=v.name,
                folder=str(result.folder),
                methods=methods,
                reductions_pct=_reductions(methods),
                split_share={k: c / n for k, c in plays.items()} if n else {},
                mean_latency_s=sum(c * s for c, s in weighted) / answered if answered else None,
                requests=int(inference.get("requests", 0)),
                lost=int(inference.get("lost", 0)),
                wall_s=wall,
                error=error,
            )
        )
    return rows


def _report_summary(scenario: Scenario, folder: Path, progress: Progress) -> dict[str, Any] | None:
    """Build the run's report as `testbed run` does (when the scenario asks for one) and return
    its summary; None when there is none. A report that cannot be built is a warning: the node
    statistics still fill the row."""
    if not scenario.report.enabled:
        return None
    from reports.build import report_after_run

    built, why_not = report_after_run(folder, scenario.report.formats, scenario.report.plots)
    if built is None:
        if (folder / names.RUN_MCAP).is_file():
            progress(f"    warning: no report: {why_not}")
        return None
    try:  # the file, as a reader of the run folder sees it (NaN as null)
        data = json.loads((folder / names.SUMMARY_FILE).read_text())
    except (OSError, ValueError) as err:
        progress(f"    warning: no summary.json in {folder}: {err}")
        return None
    return data if isinstance(data, dict) else None


def run_sweep(
    file: Path,
    sets: Sequence[str],
    out: Path | None = None,
    real: bool = False,
    progress: Progress = print,
    runs_root: Path = Path("runs"),
    duration: str | None = None,
) -> SweepReport:
    """Check every variant, run them one by one, write the report; returns it.

    Raises `BadInput` / `ScenarioError` (exit 2) before anything runs when an option, a key or
    a value is wrong. A real variant that fails is recorded in its row and the sweep goes on;
    a host that cannot run (not root) stops it (`HostError`, exit 3).
    """
    t_start = time.perf_counter()
    axes = [parse_set(s) for s in sets]
    variants = grid(axes)
    base = read_tree(file)
    if duration is not None:
        from testbed import units

        try:
            seconds = units.parse_duration(duration)
        except units.UnitError as err:
            raise BadInput(
                f"--duration: expected {units.DURATION_EXPECTED}, found {err.found}"
            ) from None
        if seconds <= 0:
            raise BadInput(f"--duration: expected a run length above 0s, found {duration!r}")
        base = shorten(base, seconds)
    scenarios: list[Scenario] = []
    for i, overrides in enumerate(variants):
        shown = label(axes, i)
        what = "--set " + " --set ".join(f"{k}={v}" for k, v in shown.items())
        scenarios.append(load_tree(variant_tree(base, overrides), file, what))
    if out is None:
        out = runs_root / f"sweep-{secrets.token_hex(3)}"
    out.mkdir(parents=True, exist_ok=True)
    (out / "variants").mkdir(exist_ok=True)
    report = SweepReport(str(file), "real" if real else "replay", axes, out=out)
    engine = _ReplayEngine()
    progress(
        f"sweep of {file}: {len(variants)} variant(s) "
        f"({' x '.join(f'{a.key} ({len(a.values)})' for a in axes)}), "
        f"{'real runs' if real else 'offline replay'}; report in {out}/"
    )
    for i, scenario in enumerate(scenarios):
        values = label(axes, i)
        shown = ", ".join(f"{k}={v}" for k, v in values.items())
        # The variant as a file beside the report: what ran, and what a run folder copies.
        variant_file = out / "variants" / f"v{i + 1:02d}.yaml"
        variant_file.write_text(
            f"# {file} with {shown}\n"
            + yaml.safe_dump(variant_tree(base, variants[i]), sort_keys=False)
        )
        scenario = dataclasses.replace(scenario, source=variant_file)
        progress(f"variant {i + 1}/{len(scenarios)}: {shown}")
        t0 = time.perf_counter()
        try:
            if real:
                rows = _real_rows(scenario, out / "runs", i, values, progress)
            else:
                rows = engine.run(scenario, out / "replay" / f"v{i + 1:02d}", i, values)
        except (BadInput, HostError):  # wrong for every variant, or this host cannot run any
            raise
        except (TestbedError, NetemError, RecordingError) as err:
            rows = [_failed_row(i, values, v.name, str(err)) for v in scenario.topology.vehicles]
        report.rows += rows
        for r in rows:
            progress(f"  {r.vehicle}: {_row_line(r)} ({time.perf_counter() - t0:.1f} s)")
    report.wall_s = time.perf_counter() - t_start
    write_report(report)
    return report


def _failed_row(index: int, values: dict[str, str], vehicle: str, error: str) -> VariantResult:
    empty: dict[str, float | None] = {"total_m": None, "mean_m": None}
    return VariantResult(
        index, values, vehicle, "", {m: dict(empty) for m in METHODS},
        {"vo": None, "dnn": None, "kalman": None}, {}, None, 0, 0, 0.0, error,
    )  # fmt: skip


def _row_line(r: VariantResult) -> str:
    if r.error:
        return f"FAILED: {r.error.splitlines()[0]}"
    e = r.methods["edgeloc"]["total_m"]
    k = r.methods["kalman"]["total_m"]
    lat = "-" if r.mean_latency_s is None else f"{1000 * r.mean_latency_s:.1f} ms"
    return (
        f"EdgeLoc total {_num(e, '.1f')} m, Kalman {_num(k, '.1f')} m, "
        f"mean latency {lat}, {r.requests} requests ({r.lost} lost)"
    )


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


# ---- the report -----------------------------------------------------------------------------


def markdown(report: SweepReport) -> str:
    keys = [a.key for a in report.axes]
    multi = len({r.vehicle for r in report.rows}) > 1
    head = [
        *keys,
        *(["vehicle"] if multi else []),
        *(f"{m} total m" for m in ("edgeloc", "kalman", "dnn", "vo")),
        "edgeloc mean m",
        *(f"vs {m}" for m in ("vo", "dnn", "kalman")),
        "split shares",
        "mean latency ms",
        "requests (lost)",
    ]
    lines = [
        f"# Sweep of `{report.scenario}` ({report.mode})",
        "",
        f"{len({r.index for r in report.rows})} variant(s); axes: "
        + ", ".join(f"`{a.key}` = {', '.join(a.texts)}" for a in report.axes)
        + f"; {report.wall_s:.1f} s.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join(" --- " for _ in head) + "|",
    ]
    for r in report.rows:
        if r.error:
            cells = [*(r.values[k] for k in keys), *([r.vehicle] if multi else [])]
            cells += [f"failed: {r.error.splitlines()[0]}"] + [""] * (len(head) - len(cells) - 1)
            lines.append("| " + " | ".join(cells) + " |")
            continue
        shares = ", ".join(
            f"{k} {100 * s:.0f}%"
            for k, s in sorted(r.split_share.items(), key=lambda x: -x[1])
            if s > 0
        )
        cells = [
            *(r.values[k] for k in keys),
            *([r.vehicle] if multi else []),
            *(_num(r.methods[m]["total_m"], ".1f") for m in ("edgeloc", "kalman", "dnn", "vo")),
            _num(r.methods["edgeloc"]["mean_m"], ".2f"),
            *(_pct(r.reductions_pct[m]) for m in ("vo", "dnn", "kalman")),
            shares or "-",
            _num(None if r.mean_latency_s is None else 1000 * r.mean_latency_s, ".1f"),
            f"{r.requests} ({r.lost})",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Reductions are EdgeLoc's against each baseline (positive: EdgeLoc is better)."]
    lines += [f"- {n}" for n in _notes(report.mode)]
    return "\n".join(lines) + "\n"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:+.1f}%"


def plot(report: SweepReport, path: Path) -> None:
    """Total position error per method (top) and mean request latency (bottom) per variant."""
    import matplotlib

    matplotlib.use("Agg")  # no display: files only
    import matplotlib.pyplot as plt

    vehicles = list(dict.fromkeys(r.vehicle for r in report.rows))
    n = len({r.index for r in report.rows})
    ticks = [
        "\n".join(f"{v}" for v in label(report.axes, i).values())
        if len(report.axes) > 1
        else label(report.axes, i)[report.axes[0].key]
        for i in range(n)
    ]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    styles = ["-", "--", ":", "-."]
    for vi, vehicle in enumerate(vehicles):
        rows = {r.index: r for r in report.rows if r.vehicle == vehicle}
        style = styles[vi % len(styles)]
        suffix = f" ({vehicle})" if len(vehicles) > 1 else ""
        for ci, m in enumerate(("edgeloc", "kalman", "dnn", "vo")):
            ys = [_nan(rows[i].methods[m]["total_m"]) if i in rows else math.nan for i in range(n)]
            # One colour per method, one line style per vehicle.
            top.plot(range(n), ys, style, marker="o", color=f"C{ci}", label=f"{m}{suffix}")
        lat = [
            _nan(None if rows.get(i) is None or rows[i].mean_latency_s is None
                 else 1000 * rows[i].mean_latency_s)  # type: ignore[operator]
            for i in range(n)
        ]  # fmt: skip
        bottom.plot(range(n), lat, style, marker="o", color="black", label=f"latency{suffix}")
    top.set_ylabel("total position error (m)")
    top.set_yscale("log")
    top.legend(fontsize=8, ncol=2)
    top.set_title(f"sweep of {Path(report.scenario).name} ({report.mode})")
    bottom.set_ylabel("mean request latency (ms)")
    bottom.set_xticks(range(n), ticks, fontsize=8)
    bottom.set_xlabel(" / ".join(a.key for a in report.axes))
    if len(vehicles) > 1:
        bottom.legend(fontsize=8)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


def write_report(report: SweepReport) -> None:
    out = report.out
    (out / "sweep.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    (out / "sweep.md").write_text(markdown(report))
    plot(report, out / "sweep.png")


__all__ = [
    "Axis",
    "SweepReport",
    "VariantResult",
    "grid",
    "load_tree",
    "parse_set",
    "run_sweep",
    "set_path",
    "shorten",
    "split_values",
    "variant_tree",
]
