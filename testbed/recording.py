"""Recording a run to one MCAP file, `runs/<id>/run.mcap`, that ROS tools and Foxglove open.

Publisher-side recording: every node process writes what it publishes (CDR bytes from
`rclpy.serialization.serialize_message`) into its own part file `runs/<id>/parts/<process>.mcap`
(`PartWriter`), and the orchestrator writes its own part (`/links/counters`, sampled from the
link backend by `CounterSampler`). No recorder subscribes to anything, so recording adds no
packet to the emulated links. At the end of the run (success, failure, Ctrl-C), or from
`testbed clean` after the orchestrator was killed, `finalise` merges the parts into `run.mcap`
ordered by log time, with:

- profile `ros2`, message encoding `cdr`, schema encoding `ros2msg` carrying the full `.msg`
  text of each type and of every type it uses (rosbag2's concatenated format, `schema_text`),
  so mcap_ros2 and rosbags decode it with no ROS installed;
- chunks compressed as the scenario's `record.compression` says (zstd, lz4 or none), and a
  summary section with statistics and indexes;
- metadata records `edgeloc.run`, `edgeloc.nodes`, `edgeloc.timeline`, `edgeloc.linktest`
  (values are strings; structured values are JSON);
- attachments: the scenario YAML, its trace files, `linktest.json`, `links.json` (the applied
  link configuration), `events.jsonl`.

Parts are written in small chunks, flushed at least every `PART_FLUSH_S`: a process killed
with SIGKILL leaves a part that `read_part` reads up to its last complete chunk. Writing
happens on a background thread, so a publisher only pays for serialising and a queue put.

What the orchestrator knows at the start and `testbed clean` needs later (scenario, seed,
backend, namespaces, trace files, compression) is kept in `parts/manifest.json`.

No rclpy import at module level: the merge and its tests need only `mcap`.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import importlib.metadata
import json
import math
import os
import platform
import queue
import re
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from testbed import __version__
from testbed.errors import TestbedError

PROFILE = "ros2"
MESSAGE_ENCODING = "cdr"
SCHEMA_ENCODING = "ros2msg"
#: rosbag2's separator between the definitions of a type and of the types it uses.
SEPARATOR = "=" * 80
LIBRARY = f"edgeloc-testbed {__version__}"

PARTS_DIR = "parts"
MANIFEST = "manifest.json"
RUN_MCAP = "run.mcap"
#: Uncompressed bytes per chunk of a part: small, so a killed writer loses little.
PART_CHUNK_BYTES = 64 * 1024
#: A part's open chunk is written out at least this often (a quiet topic is not held back).
PART_FLUSH_S = 1.0
#: Chunk size of the merged file (mcap's default; readers seek by chunk).
MERGED_CHUNK_BYTES = 1024 * 1024
#: How often the orchestrator samples the link counters.
COUNTERS_EVERY_S = 0.5
#: Log lines quoted in `edgeloc.nodes` for a node that failed.
TAIL_LINES = 20

COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}

PRIMITIVES = frozenset(
    [
        "bool",
        "byte",
        "char",
        "float32",
        "float64",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "string",
        "wstring",
    ]
)


class RecordingError(TestbedError):
    """The recording could not be written or merged."""


# ---- schemas ---------------------------------------------------------------------------------


def full_type_name(name: str) -> str:
    """`pkg/msg/Type` for `pkg/msg/Type` or `pkg/Type`."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] == "msg":
        return name
    raise RecordingError(f"not a ROS message type name: {name!r} (expected pkg/msg/Type)")


def msg_search_paths() -> list[Path]:
    """Where `.msg` files are looked for: `share/` of every ament prefix (a sourced ROS), of
    this interpreter's prefix (the PyPI ROS wheels and the built interfaces install there),
    then the repository's own interface sources (for `edgeloc_interfaces` before a build)."""
    prefixes = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [Path(sys.prefix), Path(sys.base_prefix)]
    paths = [p / "share" for p in prefixes]
    paths.append(Path(__file__).resolve().parents[1] / "nodes")
    return paths


def find_msg_file(type_name: str, search: Sequence[Path] | None = None) -> Path:
    """The `.msg` file of `pkg/msg/Type` (first found in `search`)."""
    pkg, _, name = full_type_name(type_name).split("/")
    paths = list(search) if search is not None else msg_search_paths()
    for base in paths:
        candidate = base / pkg / "msg" / f"{name}.msg"
        if candidate.is_file():
            return candidate
    raise RecordingError(
        f"no definition of {type_name} ({pkg}/msg/{name}.msg) under "
        + ", ".join(str(p) for p in paths)
    )


def _field_type(line: str) -> str | None:
    """The type of a field or constant line of a .msg (comments stripped), else None."""
    text = line.split("#", 1)[0].strip()
    if not text:
        return None
    return text.split()[0]


def msg_dependencies(text: str, package: str) -> list[str]:
    """The non-primitive types a .msg text uses, as `pkg/msg/Type`, in order of first use."""
    out: list[str] = []
    for line in text.splitlines():
        typ = _field_type(line)
        if typ is None:
            continue
        base = re.sub(r"\[[^\]]*\]$", "", typ)  # arrays: T[], T[3], T[<=3]
        base = re.sub(r"<=\d+$", "", base)  # bounded strings: string<=10
        if base in PRIMITIVES:
            continue
        if base == "Header":  # the one short name ROS 2 still resolves outside the package
            full = "std_msgs/msg/Header"
        elif "/" in base:
            full = full_type_name(base)
        else:
            full = f"{package}/msg/{base}"
        if full not in out:
            out.append(full)
    return out


def schema_text(type_name: str, search: Sequence[Path] | None = None) -> str:
    """The `ros2msg` schema of a type: its .msg text, then each type it uses (transitively,
    each once) after a separator line and `MSG: pkg/msg/Type`, as rosbag2 writes it."""
    root = full_type_name(type_name)
    texts: dict[str, str] = {}
    pending = [root]
    while pending:
        name = pending.pop(0)
        if name in texts:
            continue
        text = find_msg_file(name, search).read_text()
        texts[name] = text
        pending += [d for d in msg_dependencies(text, name.split("/")[0]) if d not in texts]
    out = texts.pop(root).rstrip("\n") + "\n"
    for name, text in texts.items():
        out += f"{SEPARATOR}\nMSG: {name}\n{text.rstrip(chr(10))}\n"
    return out


def type_name_of(msg_class: type) -> str:
    """`pkg/msg/Type` of a generated rclpy message class (module `pkg.msg._type`)."""
    package = msg_class.__module__.split(".")[0]
    return f"{package}/msg/{msg_class.__name__}"


# ---- part files ------------------------------------------------------------------------------


class PartWriter:
    """One process's part file: messages given as CDR bytes, written by a background thread.

    `write` only queues (the caller may be a real-time thread); the thread registers each
    topic's schema and channel the first time it sees it, adds messages to the current chunk,
    and writes the chunk out when it is full or `flush_s` old. `close` drains the queue and
    writes the summary. If writing fails, the next `write` raises `RecordingError` with why
    (a node then fails loudly instead of recording nothing).
    """

    def __init__(
        self,
        path: Path,
        compression: str = "lz4",
        chunk_bytes: int = PART_CHUNK_BYTES,
        flush_s: float = PART_FLUSH_S,
        search: Sequence[Path] | None = None,
    ) -> None:
        if compression not in COMPRESSION:
            raise RecordingError(
                f"compression {compression!r}: use one of {', '.join(COMPRESSION)}"
            )
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.flush_s = flush_s
        self.search = search
        self.counts: dict[str, int] = {}  # messages queued per topic
        self.error: str | None = None
        self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 (closed by the thread)
        self._writer = Writer(
            self._file, chunk_size=chunk_bytes, compression=COMPRESSION[compression]
        )
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._channels: dict[tuple[str, str], int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._queue: queue.SimpleQueue[tuple[str, str, bytes, int, int] | None] = (
            queue.SimpleQueue()
        )
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="mcap-part", daemon=True)
        self._thread.start()

    def write(
        self, topic: str, type_name: str, data: bytes, log_time_ns: int | None = None
    ) -> None:
        """Queue one message (CDR bytes of `type_name`) on `topic`, logged now by default."""
        if self.error is not None:
            raise RecordingError(f"recording to {self.path} failed: {self.error}")
        if self._closed:
            raise RecordingError(f"recording to {self.path} is closed")
        t = time.time_ns() if log_time_ns is None else log_time_ns
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self._queue.put((topic, type_name, data, t, t))

    def close(self) -> None:
        """Write what is queued and the summary; idempotent. Raises if writing failed."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join()
        if self.error is not None:
            raise RecordingError(f"recording to {self.path} failed: {self.error}")

    # -- the writer thread -----------------------------------------------------------------

    def _channel(self, topic: str, type_name: str) -> int:
        key = (topic, type_name)
        if key not in self._channels:
            if type_name not in self._schemas:
                text = schema_text(type_name, self.search)
                self._schemas[type_name] = self._writer.register_schema(
                    full_type_name(type_name), SCHEMA_ENCODING, text.encode()
                )
            self._channels[key] = self._writer.register_channel(
                topic, MESSAGE_ENCODING, self._schemas[type_name]
            )
        return self._channels[key]

    def _run(self) -> None:
        pending_since: float | None = None  # when the open chunk got its first message
        try:
            while True:
                timeout = None
                if pending_since is not None:
                    timeout = max(0.0, pending_since + self.flush_s - time.monotonic())
                try:
                    item = self._queue.get(timeout=timeout)
                except queue.Empty:
                    item = ()  # the open chunk is due
                if item is None:
                    break
                if item:
                    topic, type_name, data, log_time, publish_time = item
                    cid = self._channel(topic, type_name)
                    seq = self._sequence.get(cid, 0)
                    self._sequence[cid] = seq + 1
                    self._writer.add_message(cid, log_time, data, publish_time, sequence=seq)
                    if pending_since is None:
                        pending_since = time.monotonic()
                if pending_since is not None and time.monotonic() - pending_since >= self.flush_s:
                    self._writer.flush()  # ends the chunk: readable if we are killed now
                    pending_since = None
            self._writer.finish()
        except Exception as err:  # reported by write/close: a node must not record silently
            self.error = f"{type(err).__name__}: {err}"
        finally:
            self._file.close()


@dataclass
class PartContents:
    """What `read_part` recovered from one part file."""

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    complete: bool = False  # the file ended with its footer (the writer closed it)
    problem: str = ""  # why reading stopped early, when it did


def read_part(path: Path) -> PartContents:
    """Every schema, channel and message of a part, up to its last complete chunk.

    Reads records in file order (no index needed), so a file cut anywhere, e.g. by SIGKILL
    in the middle of a chunk, yields everything before that chunk; `problem` says where it
    stopped and `complete` whether the file was closed properly.
    """
    out = PartContents(Path(path))
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    out.schemas[record.id] = record
                elif isinstance(record, Channel):
                    out.channels[record.id] = record
                elif isinstance(record, Message):
                    out.messages.append(record)
            out.complete = True
        except (McapError, EOFError, ValueError, OSError) as err:
            out.problem = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        except Exception as err:  # a torn chunk can fail inside the decompressor
            out.problem = f"{type(err).__name__}: {err}"
    # A message whose channel was lost with a torn chunk cannot be decoded: drop it.
    out.messages = [m for m in out.messages if m.channel_id in out.channels]
    return out


# ---- merge -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Attachment:
    name: str
    media_type: str
    data: bytes
    create_time_ns: int = 0


@dataclass
class MergeReport:
    """What `merge` wrote: per-topic message counts and each part's state."""

    path: Path
    counts: dict[str, int]
    parts: dict[str, dict[str, Any]]

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def merge(
    parts: Sequence[Path],
    out: Path,
    compression: str = "zstd",
    metadata: dict[str, dict[str, str]] | None = None,
    attachments: Sequence[Attachment] = (),
) -> MergeReport:
    """Merge part files into one MCAP at `out`, messages ordered by log time (ties keep part
    order, then sequence). Schemas are shared by name, channels by (topic, schema). The file
    is written to a temporary name and renamed, so `out` is never half written."""
    if compression not in COMPRESSION:
        raise RecordingError(f"compression {compression!r}: use one of {', '.join(COMPRESSION)}")
    contents = [read_part(p) for p in parts]
    tmp = out.with_name(f".{out.name}.tmp")
    counts: dict[str, int] = {}
    with open(tmp, "wb") as f:
        writer = Writer(f, chunk_size=MERGED_CHUNK_BYTES, compression=COMPRESSION[compression])
        writer.start(profile=PROFILE, library=LIBRARY)
        schema_ids: dict[str, int] = {}
        schema_data: dict[str, bytes] = {}
        channel_ids: dict[tuple[str, str], int] = {}
        mapped: list[dict[int, int]] = []  # per part: its channel id -> merged channel id
        for part in contents:
            ids: dict[int, int] = {}
            for cid, ch in part.channels.items():
                schema = part.schemas.get(ch.schema_id)
                if schema is None:
                    raise RecordingError(f"{part.path}: channel {ch.topic} has no schema")
                if schema.name not in schema_ids:
                    schema_ids[schema.name] = writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
                    schema_data[schema.name] = schema.data
                elif schema_data[schema.name] != schema.data:
                    raise RecordingError(
                        f"{part.path}: type {schema.name} has a different definition than in "
                        "another part (mixed interface builds in one run)"
                    )
                key = (ch.topic, schema.name)
                if key not in channel_ids:
                    channel_ids[key] = writer.register_channel(
                        ch.topic, ch.message_encoding, schema_ids[schema.name], dict(ch.metadata)
                    )
                ids[cid] = channel_ids[key]
            mapped.append(ids)
        order = sorted(
            (m.log_time, i, m.sequence, j)
            for i, part in enumerate(contents)
            for j, m in enumerate(part.messages)
        )
        topic_of = {cid: topic for (topic, _), cid in channel_ids.items()}
        sequence: dict[int, int] = {}
        for _, i, _, j in order:
            m = contents[i].messages[j]
            cid = mapped[i][m.channel_id]
            seq = sequence.get(cid, 0)
            sequence[cid] = seq + 1
            writer.add_message(cid, m.log_time, m.data, m.publish_time, sequence=seq)
            counts[topic_of[cid]] = counts.get(topic_of[cid], 0) + 1
        for name, values in (metadata or {}).items():
            writer.add_metadata(name, values)
        for a in attachments:
            writer.add_attachment(a.create_time_ns, time.time_ns(), a.name, a.media_type, a.data)
        writer.finish()
    tmp.replace(out)
    report_parts = {
        p.path.name: {
            "messages": len(p.messages),
            "complete": p.complete,
            **({"problem": p.problem} if p.problem else {}),
        }
        for p in contents
    }
    return MergeReport(out, counts, report_parts)


# ---- the orchestrator's side ----------------------------------------------------------------


def parts_dir(folder: Path) -> Path:
    return Path(folder) / PARTS_DIR


def part_path(folder: Path, process: str) -> Path:
    """Where process `process` (e.g. `av1.fusion`, `orchestrator`) writes its part."""
    return parts_dir(folder) / f"{process}.mcap"


def write_json(path: Path, data: object) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(strict_json(data), indent=2, default=_json_default) + "\n")
    tmp.replace(path)


def _json_default(value: object) -> object:
    return str(value)


def strict_json(value: Any) -> Any:
    """`value` with NaN/inf floats as None: metadata must be JSON any reader parses (json.dumps
    would write the non-standard `NaN`)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [strict_json(v) for v in value]
    return value


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
    parts_dir(folder).mkdir(parents=True, exist_ok=True)
    write_json(parts_dir(folder) / MANIFEST, manifest)


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
    found: list[tuple[str, Path]] = [
        (name, folder / name)
        for name in ("scenario.yaml", "linktest.json", "links.json", "events.jsonl")
    ]
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
        lines = (folder / "events.jsonl").read_text().splitlines()
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
    names = set(processes)
    names |= {p.stem for p in (folder / "logs").glob("*.log")}
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
        if code != 0 and not (ok and code is None):
            entry["log_tail"] = _tail(folder / "logs" / f"{name}.log")
        out[name] = json.dumps(strict_json(entry), default=_json_default, allow_nan=False)
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
    pdir = parts_dir(folder)
    manifest = _read_json(pdir / MANIFEST) or {}
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
        **{k: str(v) for k, v in manifest.get("versions", {}).items()},
        "host": json.dumps(manifest.get("host", {})),
        **(notes or {}),
    }
    timeline = _lateness(folder)
    linktest = _read_json(folder / "linktest.json")
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
                "file": "linktest.json",
            }
        ),
    }
    parts = sorted(p for p in pdir.glob("*.mcap")) if pdir.is_dir() else []
    try:
        report = merge(
            parts,
            folder / RUN_MCAP,
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

    TOPIC = "/links/counters"
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
            if parts_dir(folder).is_dir():
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
