"""Recording a run, the orchestrator's side: what it writes at the start, samples while the run
goes, and merges at the end into `runs/<id>/run.mcap`, a file ROS tools and Foxglove open.

Publisher-side recording: every node process writes what it publishes into its own part file
(`nodes.recording.parts.PartWriter`), and the orchestrator writes its own part
(`/links/counters`, sampled from the link backend by `CounterSampler`). No recorder subscribes
to anything, so recording adds no packet to the emulated links. At the end of the run (success,
failure, Ctrl-C), or from `testbed clean` after the orchestrator was killed, `finalise` merges
the parts (`nodes.recording.merge`) with:

- metadata records `edgeloc.run`, `edgeloc.nodes`, `edgeloc.timeline`, `edgeloc.linktest`
  (values are strings; structured values are JSON);
- attachments: the scenario YAML, its trace files, `linktest.json`, `links.json` (the applied
  link configuration), `events.jsonl`.

What the orchestrator knows at the start and `testbed clean` needs later (scenario, seed,
backend, namespaces, trace files, compression) is kept in `parts/manifest.json`.
The format itself (names, schemas, parts, merge) lives in `nodes.recording`.

`Recording` is one run's side of it: the manifest and `links.json` (`links_config`) at the
start, the counters while the run goes, the `/traffic/*`, `/radio/*` and `/handover` parts
(each written by `write_part`) and the merge at the end.

Chunks are zstd, lz4 or none (`record.compression`), with a summary and statistics. After kill -9
of `testbed run`, `testbed clean` merges what was recorded, up to each part's last chunk.
`runs/<id>/nodes/config.json` (the settings the nodes ran with) and run.json are attachments
too, which is what lets a report be rebuilt from run.mcap alone.

Packet captures (`record: {pcap: [av1-gnb1]}` or `pcap: all`) write runs/<id>/pcap/<link>.pcapng
for each named link, both directions as they leave the link (after its impairments) from the
start of the workload to its end: one interface per direction (`<link> uplink`, `<link>
downlink`, direction flags set), raw IP, nanosecond stamps; what the link dropped is counted in
each interface's statistics block, not captured. A file being written is `<link>.pcapng.part`
until the run ends. `testbed run` prints where each file is and how many packets it holds,
run.json records it (`captures`), the report lists the files. On the userspace backend the
relays write them; on the tc backend a capture process per link listens on both veth ends and
writes a TCP super-packet that crossed the veth whole as its wire packets with their checksums
done (tests/test_sniff_root.py checks a file with tshark, checksums included;
tests/test_links_root.py a tc-backend link's capture). Every frame is one packet, as on a wire
(on N3 one G-PDU). The run test counts the frames per interface with tshark and finds the nodes'
DDS traffic dissected as RTPS.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import importlib
import importlib.metadata
import json
import math
import os
import platform
import shutil
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from netem.directions import DIRECTIONS
from nodes.recording import RecordingError
from nodes.recording import layout as names
from nodes.recording.jsonfile import dumps, write_json
from nodes.recording.merge import Attachment, MergeReport, merge
from nodes.recording.parts import PartWriter
from testbed import __version__

if TYPE_CHECKING:
    from testbed.topology import Net
    from testbed.traffic import CrossTraffic

#: How often the orchestrator samples the link counters.
COUNTERS_EVERY_S = 0.5
#: Log lines quoted in `edgeloc.nodes` for a node that failed.
TAIL_LINES = 20


def utc_text(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="milliseconds")


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def software_versions() -> dict[str, str]:
    """Versions a reader needs to judge a run, found without importing torch or rclpy."""
    distro = os.environ.get("ROS_DISTRO", "")
    rclpy = _version("ros-jazzy-rclpy") or _version("rclpy")
    if not distro and _version("ros-jazzy-rclpy"):
        distro = "jazzy"
    return {
        "testbed_version": __version__,
        "python": platform.python_version(),
        "ros_distro": distro or "unknown",
        "rclpy_version": rclpy or "not installed",
        "rmw": os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp (default)"),
        "torch_version": _version("torch") or "not installed",
        "mcap_version": _version("mcap") or "unknown",
        "kernel": " ".join(platform.uname()[2:4]),
    }


def host_capabilities(backend_reason: str) -> dict[str, Any]:
    """What the host offered the run: sch_netem (the preflight probe, cached per process, so
    free after an `auto` backend choice), the cgroup CPU controller, the CPU count."""
    from testbed import cgroups, check

    netem_ok, netem_detail = check.netem_status()
    ok, why = cgroups.available()
    ctl = cgroups.find_controller() if ok else None
    return {
        "link_backend_choice": backend_reason,
        "sch_netem": netem_ok,
        "sch_netem_detail": netem_detail,
        "cgroup": ctl.describe() if ctl is not None else f"none ({why})",
        "cgroup_version": ctl.version if ctl is not None else None,
        "cpus": os.cpu_count(),
    }


def write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    """What `finalise` needs that only the orchestrator knows, written at the run's start."""
    names.parts_dir(folder).mkdir(parents=True, exist_ok=True)
    write_json(names.parts_dir(folder) / names.MANIFEST, manifest)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _tail(path: Path, lines: int = TAIL_LINES) -> list[str]:
    try:
        return path.read_text(errors="replace").splitlines()[-lines:]
    except OSError:
        return []


def _media_type(name: str) -> str:
    suffix = Path(name).suffix.lower()
    return {
        ".yaml": "application/yaml",
        ".yml": "application/yaml",
        ".json": "application/json",
        ".jsonl": "application/x-ndjson",
        ".csv": "text/csv",
    }.get(suffix, "text/plain")


def _attachments(folder: Path, manifest: dict[str, Any]) -> list[Attachment]:
    found: list[tuple[str, Path]] = [(name, folder / name) for name in names.ATTACHED_FILES]
    for trace in manifest.get("traces", []):
        found.append((f"traces/{Path(trace).name}", Path(trace)))
    out = []
    for name, path in found:
        try:
            data = path.read_bytes()
            created = path.stat().st_mtime_ns
        except OSError:
            continue  # a step that never ran (no link test, no timeline yet)
        out.append(Attachment(name, _media_type(name), data, created))
    return out


def _lateness(folder: Path) -> dict[str, Any]:
    from testbed.timeline import lateness_stats

    applied, failed = [], 0
    try:
        lines = (folder / names.EVENTS_FILE).read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        with contextlib.suppress(ValueError):
            record = json.loads(line)
            if record.get("error"):
                failed += 1
            elif isinstance(record.get("lateness_s"), int | float):
                applied.append(float(record["lateness_s"]))
    return {"applied": len(applied), "failed": failed, "lateness": lateness_stats(applied)}


def _nodes_metadata(
    folder: Path, manifest: dict[str, Any], nodes: dict[str, Any] | None, ok: bool
) -> dict[str, str]:
    """Per node process: namespace, exit code, its stats file, last log lines if it failed."""
    processes = (nodes or {}).get("processes", {})
    # A vehicle's process holds its nodes (`testbed.nodeprocs`): its nodes are listed, each
    # naming it, and its own log is in run.json's containers, not a node here.
    containers = (nodes or {}).get("containers", {})
    inside = {n: c for c, info in containers.items() for n in info.get("nodes", [])}
    names = set(processes)
    names |= {p.stem for p in (folder / "logs").glob("*.log")} - set(containers)
    namespaces = manifest.get("namespaces", {})
    out: dict[str, str] = {}
    for name in sorted(names):
        proc = processes.get(name, {})
        code = proc.get("exit_code")
        stats = proc.get("stats") or _read_json(folder / "nodes" / f"{name}.json") or {}
        entry: dict[str, Any] = {
            "namespace": namespaces.get(name.split(".")[0], ""),
            "exit_code": code,
            "stats": stats,
        }
        if name in inside:
            entry["process"] = inside[name]
        if code != 0 and not (ok and code is None):
            entry["log_tail"] = _tail(folder / "logs" / f"{name}.log")
        out[name] = dumps(entry, indent=None)
    return out


def finalise(
    folder: Path,
    status: str,
    nodes: dict[str, Any] | None = None,
    ended: float | None = None,
    keep_parts_on_error: bool = True,
    notes: dict[str, str] | None = None,
) -> MergeReport:
    """Merge `folder`'s parts into `run.mcap` with the run's metadata and attachments, then
    remove `parts/` (kept, with the error raised, when the merge fails).

    `status`: "ok", "failed: <why>" or "interrupted..."; `nodes`: the supervisor's summary when
    the orchestrator has it (exit codes); without it (from `testbed clean`) stats come from
    the nodes' own files. `notes` are added to `edgeloc.run` (e.g. why a topic is missing).
    """
    folder = Path(folder)
    pdir = names.parts_dir(folder)
    manifest = _read_json(pdir / names.MANIFEST) or {}
    ended = time.time() if ended is None else ended
    started = float(manifest.get("started", ended))
    run = {
        "run_id": str(manifest.get("run_id", folder.name)),
        "scenario": str(manifest.get("scenario", "")),
        "seed": str(manifest.get("seed", "")),
        "link_backend": str(manifest.get("link_backend", "")),
        "status": status,
        "started": utc_text(started),
        "ended": utc_text(ended),
        "duration_s": f"{ended - started:.3f}",
        "compression": str(manifest.get("compression", "zstd")),
        "images": str(bool(manifest.get("images", False))).lower(),
        "edgeloc_vehicles": ",".join(manifest.get("edgeloc_vehicles", [])),
        **{k: str(v) for k, v in manifest.get("versions", {}).items()},
        "host": json.dumps(manifest.get("host", {})),
        **({"channel": json.dumps(manifest["channel"])} if manifest.get("channel") else {}),
        **(notes or {}),
    }
    timeline = _lateness(folder)
    linktest = _read_json(folder / names.LINKTEST_FILE)
    metadata = {
        "edgeloc.run": run,
        "edgeloc.nodes": _nodes_metadata(folder, manifest, nodes, status == "ok"),
        "edgeloc.timeline": {
            "events": str(manifest.get("timeline_events", "")),
            "applied": str(timeline["applied"]),
            "failed": str(timeline["failed"]),
            "lateness": json.dumps(timeline["lateness"]),
        },
        "edgeloc.linktest": (
            {"ran": "false"}
            if linktest is None
            else {
                "ran": "true",
                "ok": str(bool(linktest.get("ok"))).lower(),
                "seconds": str(linktest.get("seconds", "")),
                "file": names.LINKTEST_FILE,
            }
        ),
    }
    parts = sorted(p for p in pdir.glob("*.mcap")) if pdir.is_dir() else []
    try:
        report = merge(
            parts,
            folder / names.RUN_MCAP,
            compression=run["compression"],
            metadata=metadata,
            attachments=_attachments(folder, manifest),
        )
    except Exception as err:
        if not keep_parts_on_error:
            shutil.rmtree(pdir, ignore_errors=True)
        raise RecordingError(
            f"could not merge the recording of {folder} ({err}); the parts are in {pdir}"
        ) from err
    shutil.rmtree(pdir, ignore_errors=True)
    return report


# ---- link counters ---------------------------------------------------------------------------


def counter_rows(link: str, counters: dict[str, Any]) -> list[dict[str, Any]]:
    """LinkCounters fields per direction from a userspace relay's `counters` reply."""
    rows = []
    for direction, short in (("uplink", "up"), ("downlink", "down")):
        c = counters.get(direction)
        if not c:
            continue
        total = c.get("total", c)
        rows.append(
            {
                "link": link,
                "direction": short,
                "packets_in": int(total.get("packets_in", 0)),
                "bytes_in": int(total.get("bytes_in", 0)),
                "packets_out": int(total.get("packets_out", 0)),
                "bytes_out": int(total.get("bytes_out", 0)),
                "packets_dropped": int(sum(total.get("dropped_packets", {}).values())),
                "bytes_dropped": int(sum(total.get("dropped_bytes", {}).values())),
                "queue_packets": int(c.get("queued", 0)),
            }
        )
    return rows


class CounterSampler:
    """Samples `read()` (rows of LinkCounters fields) every `every_s` on a thread and writes
    each row through `encode` (row, time in s -> CDR bytes) into `part` on `/links/counters`.

    Reads go over the relays' unix control sockets in the host namespace: no packet on the
    emulated links. A read that fails (a relay gone at teardown) is counted, not raised: the
    run's own checks report dead relays.
    """

    TOPIC = names.LINK_COUNTERS_TOPIC
    TYPE = "edgeloc_interfaces/msg/LinkCounters"

    def __init__(
        self,
        part: PartWriter,
        read: Callable[[], Iterable[dict[str, Any]]],
        encode: Callable[[dict[str, Any], float], bytes],
        every_s: float = COUNTERS_EVERY_S,
    ) -> None:
        self.part, self.read, self.encode, self.every_s = part, read, encode, every_s
        self.samples = 0
        self.errors = 0
        self.last_error = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="link-counters", daemon=True)

    def start(self) -> CounterSampler:
        self._thread.start()
        return self

    def sample(self) -> None:
        t = time.time()
        try:
            rows = list(self.read())
        except Exception as err:
            self.errors += 1
            self.last_error = str(err)
            return
        for row in rows:
            self.part.write(self.TOPIC, self.TYPE, self.encode(row, t), int(t * 1e9))
        self.samples += 1

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self.sample()

    def stop(self) -> None:
        if self._thread.is_alive():
            self._stop.set()
            self._thread.join(timeout=5)


# ---- one run's recording ---------------------------------------------------------------------

#: What `/traffic/<flow>` carries.
TRAFFIC_TYPE = "edgeloc_interfaces/msg/TrafficSample"
RADIO_TYPE = "edgeloc_interfaces/msg/RadioState"
HANDOVER_TYPE = "edgeloc_interfaces/msg/Handover"

#: (topic, ROS message, log time in ns) per message of a part.
Messages = Iterable[tuple[str, Any, int]]


def write_part(
    folder: Path, name: str, type_name: str, messages: Callable[[Any], Messages]
) -> None:
    """Write a part of ROS messages of one type (`edgeloc_interfaces/msg/RadioState`, say) into
    `folder`'s parts: `messages(cls)` makes them with the type's message class."""
    from rclpy.serialization import serialize_message

    package, _, cls_name = type_name.partition("/msg/")
    cls = getattr(importlib.import_module(f"{package}.msg"), cls_name)
    part = PartWriter(names.part_path(folder, name))
    try:
        for topic, msg, t_ns in messages(cls):
            part.write(topic, type_name, serialize_message(msg), t_ns)
    finally:
        part.close()


def links_config(net: Net, backend: str) -> dict[str, Any]:
    """`links.json` of the run folder: per link and direction the applied profile, and how the
    backend realises it (the relay's command line and stages, or the equivalent tc commands)."""
    ctl = net.control
    out: dict[str, Any] = {"backend": backend, "links": {}}
    if ctl is None:
        return out
    for name, link in net.links.items():
        entry: dict[str, Any] = {
            "kind": link.kind,
            "lower": link.lower.name,
            "upper": link.upper.name,
            "profiles": {d: ctl.profile(name, d).to_dict() for d in DIRECTIONS},
        }
        entry.update(ctl.realisation(name))
        out["links"][name] = entry
    if ctl.backend == "tc":
        try:
            out["tc_commands"] = ctl.commands()
        except Exception as err:
            out["tc_commands"] = f"unavailable: {err}"
    return out


class Recording:
    """The orchestrator's side of a run's recording (see the module doc): the manifest, its
    own part with the link counters, and the final merge."""

    def __init__(
        self, net: Net, folder: Path, backend: str, progress: Callable[[str], None]
    ) -> None:
        from testbed import mobility
        from testbed.scenario.model import TraceEvent

        scenario = net.scenario
        self.folder, self.progress, self.net = folder, progress, net
        self.sampler: CounterSampler | None = None
        self.part: PartWriter | None = None
        self.counters_note = ""
        reason = net.link_backend.reason if net.link_backend is not None else backend
        write_manifest(
            folder,
            {
                "run_id": net.run_id,
                "scenario": scenario.name,
                "seed": scenario.seed,
                "link_backend": backend,
                "started": time.time(),
                "compression": scenario.record.compression,
                "images": scenario.record.images,
                "versions": software_versions(),
                "host": host_capabilities(reason),
                "namespaces": {n.name: n.netns for n in net.nodes.values()},
                "traces": sorted(
                    {str(e.path) for e in scenario.timeline if isinstance(e, TraceEvent)}
                ),
                "timeline_events": len(scenario.timeline),
                "edgeloc_vehicles": [v.name for v in scenario.edgeloc_vehicles()],
                "channel": mobility.describe(scenario),
            },
        )
        write_json(folder / names.LINKS_CONFIG_FILE, links_config(net, backend))

    def start_counters(self, ros_ok: bool) -> None:
        """Sample the link counters into `/links/counters` (userspace relays; the tc
        backend's qdisc statistics are not read, as in run.json's link_counters)."""
        ctl = self.net.control
        if ctl is None or not ctl.counts:
            self.counters_note = "not recorded: the tc backend's qdisc counters are not read"
            return
        if not ros_ok:
            self.counters_note = "not recorded: rclpy/edgeloc_interfaces not importable"
            return
        from edgeloc_interfaces.msg import LinkCounters
        from rclpy.serialization import serialize_message

        from nodes.ros.common import to_stamp

        backend = self.net.control.backend  # type: ignore[union-attr]

        def read() -> list[dict[str, Any]]:
            return [
                row
                for link in self.net.links
                for row in counter_rows(link, ctl.counters(link) or {})
            ]

        def encode(row: dict[str, Any], t: float) -> bytes:
            return serialize_message(LinkCounters(stamp=to_stamp(t), backend=backend, **row))

        self.part = PartWriter(names.part_path(self.folder, "orchestrator"))
        self.sampler = CounterSampler(self.part, read, encode)
        self.sampler.sample()  # one sample now: the counters at the nodes' start
        self.sampler.start()

    def stop_counters(self) -> None:
        """Stop sampling (before the links go away), close the part, and add the profiles the
        timeline left on each link to links.json (`final_profiles`)."""
        if self.sampler is not None:
            self.sampler.stop()
            self.sampler.sample()  # and one at the end
            self.sampler = None
            self._final_profiles()
        if self.part is not None:
            self.part.close()

    def _final_profiles(self) -> None:
        ctl, path = self.net.control, self.folder / names.LINKS_CONFIG_FILE
        if ctl is None:
            return
        try:
            data = json.loads(path.read_text())
            data["final_profiles"] = {
                name: {d: ctl.profile(name, d).to_dict() for d in DIRECTIONS}
                for name in self.net.links
            }
            write_json(path, data)
        except (OSError, ValueError) as err:
            self.progress(f"  warning: links.json not updated: {err}")

    def _write_part(
        self,
        what: str,
        name: str,
        type_name: str,
        messages: Callable[[Any], Messages],
        ros_ok: bool,
    ) -> None:
        if not ros_ok:
            self.progress(f"  warning: {what} not recorded: rclpy/edgeloc_interfaces missing")
            return
        write_part(self.folder, name, type_name, messages)

    def record_traffic(self, traffic: CrossTraffic, ros_ok: bool) -> None:
        """Write the flows' samples as `/traffic/<flow>` (TrafficSample) into their own part."""
        if not traffic:
            return

        def number(value: Any) -> float:
            return math.nan if value is None else float(value)

        def messages(TrafficSample: Any) -> Messages:
            from nodes.ros.common import to_stamp

            for flow, s in traffic.samples():
                t_ns = int(s.get("time_ns") or time.time_ns())
                msg = TrafficSample(
                    stamp=to_stamp(t_ns / 1e9),
                    flow=flow.name,
                    kind=flow.kind,
                    role=str(s.get("role", "")),
                    t=number(s.get("t")),
                    bytes=int(s.get("bytes") or 0),
                    packets=int(s.get("packets") or 0),
                    rate_bps=number(s.get("rate_bps")),
                    goodput_bps=number(s.get("goodput_bps")),
                    loss=number(s.get("loss")),
                    delay_ms=number(s.get("delay_ms")),
                    rtt_ms=number(s.get("rtt_ms")),
                    late=int(s.get("late") or 0),
                )
                yield f"/traffic/{flow.name}", msg, t_ns

        self._write_part("/traffic/*", "traffic", TRAFFIC_TYPE, messages, ros_ok)

    def record_radio(self, started_epoch_s: float | None, ros_ok: bool) -> None:
        """Write each vehicle's channel steps up to now as `/radio/<vehicle>` (RadioState),
        stamped where the timeline placed them, into their own part."""
        scenario = self.net.scenario
        if scenario.channel is None or started_epoch_s is None:
            return

        played = min(scenario.duration_s, time.time() - started_epoch_s)

        def messages(RadioState: Any) -> Messages:
            from nodes.ros.common import to_stamp
            from testbed import mobility

            for plan in mobility.plans_of(scenario).values():
                for s in plan.steps:
                    if s.t > played:
                        break
                    t = started_epoch_s + s.t
                    msg = RadioState(
                        stamp=to_stamp(t),
                        vehicle=plan.vehicle,
                        cell=s.serving,
                        x=s.x,
                        y=s.y,
                        rsrp_dbm=s.rsrp_dbm,
                        sinr_db=s.sinr_db,
                        cqi=s.cqi,
                        mcs=s.mcs,
                        bler=s.bler,
                        ul_sinr_db=s.ul_sinr_db,
                        ul_mcs=s.ul_mcs,
                        ul_bler=s.ul_bler,
                    )
                    yield names.radio_topic(plan.vehicle), msg, int(t * 1e9)

        self._write_part("/radio/*", "radio", RADIO_TYPE, messages, ros_ok)

    def record_handovers(
        self, started_epoch_s: float | None, handovers: list[dict[str, Any]], ros_ok: bool
    ) -> None:
        """Write the applied handovers (`handovers_applied`) as `/handover` (Handover),
        stamped when each took effect, into their own part."""
        if not handovers or started_epoch_s is None:
            return

        def messages(Handover: Any) -> Messages:
            from nodes.ros.common import to_stamp

            for h in handovers:
                t = started_epoch_s + h["applied_s"]
                msg = Handover(
                    stamp=to_stamp(t),
                    vehicle=h["vehicle"],
                    source=h["source"],
                    target=h["target"],
                    scheduled_s=h["scheduled_s"],
                    lateness_s=h["lateness_s"],
                    interruption_s=h["interruption_s"],
                    lossless=h["lossless"],
                    error=h["error"] or "",
                )
                yield names.HANDOVER_TOPIC, msg, int(t * 1e9)

        self._write_part("/handover", "handover", HANDOVER_TYPE, messages, ros_ok)

    def finish(self, status: str, nodes: dict[str, Any] | None) -> None:
        """Merge the parts into run.mcap (raises RecordingError if that fails)."""
        try:
            self.stop_counters()
        except RecordingError as err:
            self.progress(f"  warning: {err}")
        t = time.perf_counter()
        notes = {"link_counters": self.counters_note} if self.counters_note else None
        report = finalise(self.folder, status, nodes=nodes, notes=notes)
        size = report.path.stat().st_size
        self.progress(
            f"  recorded {report.messages} messages on {len(report.counts)} topics into "
            f"{report.path} ({size / 1e6:.2f} MB) in {time.perf_counter() - t:.2f} s"
            + (f"; link counters {self.counters_note}" if self.counters_note else "")
        )


# ---- after a crash ---------------------------------------------------------------------------

#: The status `testbed clean` records for a run whose orchestrator died.
ORPHANED = "interrupted: the orchestrator died; finalised by `testbed clean`"


def unfinished_folders(include_detached: bool = False) -> list[Path]:
    """Run folders whose recording was never merged: runs `testbed clean` is about to remove
    (dead, or detached with `include_detached`) that recorded a folder with `parts/` in it.
    Call before the clean: it deletes the state files that name the folders."""
    from testbed import state as st

    out = []
    for run in st.list_runs():
        live = run.liveness()
        if run.folder and (live == "dead" or (include_detached and live == "detached")):
            folder = Path(run.folder)
            if names.parts_dir(folder).is_dir():
                out.append(folder)
    return out


def finalise_orphans(folders: Sequence[Path]) -> list[str]:
    """Merge each folder's parts (after `clean` stopped its nodes, which closes their parts)
    into run.mcap; one line per folder saying what was written or why not."""
    lines = []
    for folder in folders:
        try:
            report = finalise(folder, ORPHANED)
        except RecordingError as err:
            lines.append(f"error: {err}")
            continue
        torn = [name for name, p in report.parts.items() if not p["complete"]]
        lines.append(
            f"recording of {folder.name} finalised: {report.path} ({report.messages} messages"
            + (f"; read up to the last chunk of {', '.join(torn)}" if torn else "")
            + ")"
        )
    return lines
