"""Read a run's `run.mcap` into plain, typed arrays (`RunData`), tolerating damage.

The file is read front to back with `mcap`'s stream reader (not through the summary section),
so a recording cut short — Ctrl-C, a crashed recorder, a full disk — still yields every record
written before the cut; `RunData.complete` is False then and `problems` says why. Messages are
decoded from their `ros2msg` schema text with `mcap_ros2`'s decoder, so no ROS install is
needed. A message that does not decode is counted, not fatal.

Topics read (named in `nodes.recording.layout`): `/<vehicle>/gt`, `/<vehicle>/vo`,
`/<vehicle>/dnn_answer` and `/<vehicle>/pose` (PoseEstimate; `pose` carries one message per
method per frame), `/<vehicle>/split_decision`, `/<vehicle>/detector`, `/<vehicle>/inference`,
`/links/events`, `/links/counters`, `/radio/<vehicle>` (RadioState), `/handover` (Handover);
metadata `edgeloc.run`, `edgeloc.nodes`, `edgeloc.timeline`, `edgeloc.linktest` (values
JSON-encoded where structured); attachments by name, `linktest.json` and `links.json` (the
links' profiles, whose NR radios `RunData.link_radios` rebuilds) decoded. Times are kept as
float seconds since the epoch; `RunData.t0` is the origin the report measures run time from.
"""

from __future__ import annotations

import json
import math
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, get_type_hints

import numpy as np
from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from numpy.typing import NDArray

from netem.directions import DIRECTIONS
from netem.nr.radio import Radio
from nodes.recording.layout import (
    HANDOVER_TOPIC,
    LINK_COUNTERS_TOPIC,
    LINK_EVENTS_TOPIC,
    LINKS_CONFIG_FILE,
    RUN_FILE,
    RUN_MCAP,
    VEHICLE_TOPICS,
    radio_topic,
)
from reports.errors import ReportInputError


def _stamp(msg: Any) -> float:
    """builtin_interfaces/Time as float seconds."""
    st = getattr(msg, "stamp", None)
    if st is None:
        return math.nan
    return float(st.sec) + float(st.nanosec) * 1e-9


@dataclass
class PoseTrack:
    """One method's poses of one vehicle, one row per frame, sorted by frame id."""

    frame: NDArray[np.int64]
    stamp: NDArray[np.float64]  # the instant the pose is for (capture time of the frame)
    pose: NDArray[np.float64]  # (N, 3) x, y, yaw
    latency_s: NDArray[np.float64]  # age of the newest DNN answer used (NaN: none)
    log_time: NDArray[np.float64]  # when the recorder received it

    @classmethod
    def from_rows(
        cls, rows: list[tuple[int, float, float, float, float, float, float]], dedup: bool = True
    ) -> PoseTrack:
        if dedup:
            # A frame seen twice (a republished message) keeps its last copy: one row per frame.
            by_frame = {r[0]: r for r in rows}
            ordered = [by_frame[f] for f in sorted(by_frame)]
        else:  # every message counts (DNN answers: gaps are measured between arrivals)
            ordered = sorted(rows, key=lambda r: (r[6], r[0]))
        a = np.array(ordered, dtype=np.float64).reshape(-1, 7)
        return cls(
            frame=a[:, 0].astype(np.int64),
            stamp=a[:, 1],
            pose=a[:, 2:5].copy(),
            latency_s=a[:, 5],
            log_time=a[:, 6],
        )

    def __len__(self) -> int:
        return len(self.frame)


@dataclass
class Decision:
    """One SplitDecision: what the learner chose for a request."""

    t: float
    log_time: float
    frame_id: int
    chosen: str
    chosen_index: int
    rule: str
    arm_names: list[str]
    last_latency_s: float
    plays: int
    plays_total: int


@dataclass
class DetectorUpdate:
    t: float
    arm: str
    kl: float
    threshold: float
    consecutive: int
    required: int
    reset: bool
    at_play: int


@dataclass
class Inference:
    """One request of thread 2 and its outcome (InferenceResult)."""

    t: float
    log_time: float
    frame_id: int
    split: str
    split_index: int
    payload_bytes: int
    head_s: float
    edge_compute_s: float
    latency_s: float  # NaN when no answer came
    ok: bool
    timed_out: bool
    error: str


@dataclass
class LinkEventRec:
    t: float
    scheduled_s: float
    lateness_s: float
    action: str
    target: str
    direction: str
    changes: list[tuple[str, str]]


#: The numeric fields of a RadioState that a `RadioSeries` keeps, each an array.
RADIO_NUMBERS = (
    "x", "y", "rsrp_dbm", "sinr_db", "cqi", "mcs", "bler", "ul_sinr_db", "ul_mcs", "ul_bler",
)  # fmt: skip


@dataclass
class RadioSeries:
    """One vehicle's channel steps (`/radio/<vehicle>`, RadioState), in time order."""

    vehicle: str
    t: NDArray[np.float64]  # stamps, wall clock
    cell: list[str]  # serving cell per step
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    rsrp_dbm: NDArray[np.float64]
    sinr_db: NDArray[np.float64]
    cqi: NDArray[np.float64]
    mcs: NDArray[np.float64]
    bler: NDArray[np.float64]
    ul_sinr_db: NDArray[np.float64]
    ul_mcs: NDArray[np.float64]
    ul_bler: NDArray[np.float64]

    @classmethod
    def from_rows(cls, vehicle: str, rows: list[tuple[Any, ...]]) -> RadioSeries:
        """From `_radio_row`s: (stamp, cell, *the `RADIO_NUMBERS` in order)."""
        rows = sorted(rows, key=lambda r: r[0])
        a = np.array([[r[0], *r[2:]] for r in rows], dtype=np.float64)
        a = a.reshape(-1, 1 + len(RADIO_NUMBERS))
        numbers = {name: a[:, 1 + i] for i, name in enumerate(RADIO_NUMBERS)}
        return cls(vehicle, a[:, 0], [str(r[1]) for r in rows], **numbers)

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class HandoverRec:
    """One applied handover (`/handover`, Handover). Its fields after `t` are the message's
    fields of the same names, read by `_handover` from this class alone: a field added here
    is read from the message without another list to keep in step."""

    t: float  # stamp: when it took effect (both links stopped, routes moved), wall clock
    vehicle: str
    source: str  # the gNB it left
    target: str  # the gNB it went to
    scheduled_s: float  # when A3 triggered, seconds since the timeline's start
    lateness_s: float  # applied - scheduled
    interruption_s: float  # how long the user plane stopped
    lossless: bool  # in-flight data delivered late (True) or lost (False)
    error: str  # empty when it was applied


@dataclass
class CounterSeries:
    """Cumulative counters of one direction of one link, sampled over time."""

    link: str
    direction: str  # "up" or "down" (normalised from up/uplink, down/downlink)
    backend: str
    t: NDArray[np.float64]
    bytes_in: NDArray[np.float64]
    bytes_out: NDArray[np.float64]
    packets_in: NDArray[np.float64]
    packets_out: NDArray[np.float64]
    packets_dropped: NDArray[np.float64]

    def rate_mbit(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Delivered rate (Mbit/s) between consecutive samples, at the interval midpoints.

        A counter that went backwards (a relay restarted) gives no rate for that interval."""
        if len(self.t) < 2:
            return np.zeros(0), np.zeros(0)
        dt = np.diff(self.t)
        db = np.diff(self.bytes_out)
        good = (dt > 0) & (db >= 0)
        mid = (self.t[1:] + self.t[:-1]) / 2
        return mid[good], db[good] * 8.0 / dt[good] / 1e6


@dataclass
class VehicleData:
    name: str
    tracks: dict[str, PoseTrack] = field(default_factory=dict)  # "gt", "vo", "dnn_answer", methods
    decisions: list[Decision] = field(default_factory=list)
    detector: list[DetectorUpdate] = field(default_factory=list)
    inference: list[Inference] = field(default_factory=list)

    @property
    def gt(self) -> PoseTrack | None:
        return self.tracks.get("gt")

    def methods(self) -> list[str]:
        """Methods published on `/<vehicle>/pose`, the paper's four first, then the rest."""
        order = ["vo", "dnn", "kalman", "edgeloc"]
        names = [m for m in self.tracks if m not in ("gt", "vo_raw", "dnn_answer")]
        return [m for m in order if m in names] + sorted(set(names) - set(order))


@dataclass
class RunData:
    """Everything the report uses from one MCAP."""

    path: Path
    complete: bool  # the file has its footer and read without error
    problems: list[str]  # why it is not complete, decoding trouble
    run: dict[str, Any]  # metadata "edgeloc.run"
    nodes: dict[str, Any]  # metadata "edgeloc.nodes"
    timeline: Any  # metadata "edgeloc.timeline"
    linktest: dict[str, Any] | None  # the link self-test table (attachment linktest.json)
    linktest_meta: dict[str, Any]  # metadata "edgeloc.linktest" (ran, ok, seconds, file)
    metadata: dict[str, dict[str, str]]  # every metadata record, raw
    attachments: dict[str, bytes]
    topics: dict[str, int]  # topic -> messages read
    schemas: dict[str, str]  # topic -> schema name
    decode_errors: int
    vehicles: dict[str, VehicleData]
    link_events: list[LinkEventRec]
    counters: list[CounterSeries]
    first_log_time: float | None
    last_log_time: float | None
    radio: dict[str, RadioSeries] = field(default_factory=dict)  # vehicle -> /radio/<vehicle>
    handovers: list[HandoverRec] = field(default_factory=list)  # /handover, in time order
    #: The attachment links.json (`testbed.recording.links_config`: per link its profiles per
    #: direction as applied at the start, `final_profiles` as the timeline left them); None
    #: when the run did not attach it (runs older than the attachment).
    links_config: dict[str, Any] | None = None
    #: (link, direction) -> the NR radio that direction started the run with, rebuilt from
    #: links.json: what the report needs to say what an air link carried at a step's MCS.
    link_radios: dict[tuple[str, str], Radio] = field(default_factory=dict)
    #: The run's run.json (`read_run_json`): paths to the edge, apps, cross-traffic,
    #: captures, the timeline's start; {} when the run ended before writing it.
    run_json: dict[str, Any] = field(default_factory=dict)

    @property
    def t0(self) -> float:
        """The origin of run time in the report: the first ground-truth (else raw VO, else any
        pose) stamp, which is when the workload started; else the first message."""
        for keys in (("gt",), ("vo_raw",), None):
            starts = [
                float(t.stamp.min())
                for v in self.vehicles.values()
                for name, t in v.tracks.items()
                if len(t) and (keys is None or name in keys)
            ]
            if starts:
                return min(starts)
        return self.first_log_time or 0.0

    @property
    def status(self) -> str:
        return str(self.run.get("status", "unknown (no edgeloc.run metadata)"))

    @property
    def partial(self) -> bool:
        """The recording misses the end of the run: cut short, or the run was interrupted."""
        return not self.complete or self.status.startswith("interrupted")


def _json_or_text(value: str) -> Any:
    """A metadata value: JSON objects/arrays decoded, any other text kept as it is (a run id
    such as "123456" must stay a string)."""
    text = value.strip() if isinstance(value, str) else value
    if isinstance(text, str) and text[:1] in ("{", "["):
        try:
            return json.loads(text)
        except ValueError:
            return value
    return value


def _records(path: Path, problems: list[str]) -> Iterator[Any]:
    """Every record of the file in order; stops quietly (noting why) where the file breaks."""
    try:
        with open(path, "rb") as f:
            reader = StreamReader(f, record_size_limit=None)
            yield from reader.records
    except Exception as err:  # a cut file ends in EndOfFile, a cut chunk in a zstd error
        problems.append(f"the file ends early or is damaged ({type(err).__name__}: {err})")


def read_run(path: Path | str) -> RunData:
    """Read `path` (a run.mcap, or a run folder holding one)."""
    p = Path(path)
    if p.is_dir():
        p = p / RUN_MCAP
    if not p.is_file():
        raise ReportInputError(f"{p}: no such file (a run folder holds {RUN_MCAP})")
    with open(p, "rb") as f:
        magic = f.read(8)
    if magic[:5] != b"\x89MCAP":
        raise ReportInputError(f"{p}: not an MCAP file (it does not start with the MCAP magic)")

    problems: list[str] = []
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    decoders: dict[int, Callable[[bytes], Any] | None] = {}
    factory = DecoderFactory()
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    topics: Counter[str] = Counter()
    decode_errors: Counter[str] = Counter()
    rows: dict[tuple[str, str], list[tuple[int, float, float, float, float, float, float]]]
    rows = defaultdict(list)
    vehicles: dict[str, VehicleData] = {}
    link_events: list[LinkEventRec] = []
    counter_rows: dict[tuple[str, str], list[tuple[float, ...]]] = defaultdict(list)
    counter_backend: dict[tuple[str, str], str] = {}
    radio_rows: dict[str, list[tuple[Any, ...]]] = defaultdict(list)
    handovers: list[HandoverRec] = []
    seen_footer = seen_data_end = False
    first_log: float | None = None
    last_log: float | None = None

    def vehicle(name: str) -> VehicleData:
        if name not in vehicles:
            vehicles[name] = VehicleData(name)
        return vehicles[name]

    read_problems: list[str] = []
    for rec in _records(p, read_problems):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Metadata):
            metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Attachment):
            attachments[rec.name] = bytes(rec.data)
        elif isinstance(rec, DataEnd):
            seen_data_end = True
        elif isinstance(rec, Footer):
            seen_footer = True
        elif isinstance(rec, Message):
            ch = channels.get(rec.channel_id)
            if ch is None:
                decode_errors["<unknown channel>"] += 1
                continue
            if rec.channel_id not in decoders:
                try:
                    decoders[rec.channel_id] = factory.decoder_for(
                        ch.message_encoding, schemas.get(ch.schema_id)
                    )
                except Exception as err:
                    problems.append(f"{ch.topic}: cannot build a decoder ({err})")
                    decoders[rec.channel_id] = None
            decode = decoders[rec.channel_id]
            if decode is None:
                decode_errors[ch.topic] += 1
                continue
            try:
                msg = decode(rec.data)
            except Exception:
                decode_errors[ch.topic] += 1
                continue
            log_t = rec.log_time * 1e-9
            try:
                if ch.topic.startswith(RADIO_PREFIX):
                    radio_rows[ch.topic[len(RADIO_PREFIX) :]].append(_radio_row(msg))
                elif ch.topic == HANDOVER_TOPIC:
                    handovers.append(_handover(msg))
                else:
                    _take(
                        ch.topic,
                        msg,
                        log_t,
                        rows,
                        vehicle,
                        link_events,
                        counter_rows,
                        counter_backend,
                    )
            except (AttributeError, TypeError, ValueError):
                # A known topic with another type than the report expects: count it as
                # undecodable instead of failing the whole report.
                decode_errors[ch.topic] += 1
                continue
            topics[ch.topic] += 1
            first_log = log_t if first_log is None else min(first_log, log_t)
            last_log = log_t if last_log is None else max(last_log, log_t)

    if not (schemas or channels or metadata or attachments):
        # Only the magic, or a header and a footer: no run, no metadata, nothing to report.
        why = "; ".join(read_problems) or "an empty recording"
        raise ReportInputError(f"{p}: no records in this MCAP ({why}): nothing to report")
    cut = bool(read_problems) or not seen_footer
    problems[:0] = read_problems
    if not seen_footer:
        problems.insert(0, "the recording was not finished (no MCAP footer): data is partial")
    elif not seen_data_end:
        problems.append("the file has no data-end record")
    for topic, n in sorted(decode_errors.items()):
        problems.append(f"{topic}: {n} message(s) could not be decoded")

    for (vname, key), r in rows.items():
        vehicle(vname).tracks[key] = PoseTrack.from_rows(r, dedup=key != "dnn_answer")
    for vd in vehicles.values():
        vd.decisions.sort(key=lambda d: (d.t, d.frame_id))
        vd.detector.sort(key=lambda d: (d.t, d.at_play))
        vd.inference.sort(key=lambda i: (i.t, i.frame_id))
    link_events.sort(key=lambda e: (e.t, e.scheduled_s))
    counters = []
    for (link, direction), crow in sorted(counter_rows.items()):
        a = np.array(sorted(crow), dtype=np.float64).reshape(-1, 6)
        counters.append(
            CounterSeries(
                link,
                direction,
                counter_backend[(link, direction)],
                a[:, 0],
                a[:, 1],
                a[:, 2],
                a[:, 3],
                a[:, 4],
                a[:, 5],
            )
        )

    run_meta = _unpack_named(metadata, "edgeloc.run")
    nodes_meta = _unpack_named(metadata, "edgeloc.nodes")
    timeline = _unpack_named(metadata, "edgeloc.timeline")
    # The self-test table is the linktest.json attachment; the metadata record only says
    # whether it ran and its verdict (or, from other writers, may hold the table itself).
    linktest_meta = _unpack_named(metadata, "edgeloc.linktest")
    linktest: Any = None
    if "linktest.json" in attachments:
        try:
            linktest = json.loads(attachments["linktest.json"].decode("utf-8", "replace"))
        except ValueError:
            problems.append("attachment linktest.json is not valid JSON")
    elif isinstance(linktest_meta.get("links"), list):
        linktest = linktest_meta
    links_config: Any = None
    if LINKS_CONFIG_FILE in attachments:
        try:
            links_config = json.loads(attachments[LINKS_CONFIG_FILE].decode("utf-8", "replace"))
        except ValueError:
            problems.append(f"attachment {LINKS_CONFIG_FILE} is not valid JSON")
    links_config = links_config if isinstance(links_config, dict) else None

    return RunData(
        path=p,
        complete=not cut,
        problems=problems,
        run=run_meta,
        nodes=nodes_meta,
        timeline=timeline,
        linktest=linktest if isinstance(linktest, dict) else None,
        linktest_meta=linktest_meta,
        metadata=metadata,
        attachments=attachments,
        topics=dict(sorted(topics.items())),
        schemas={
            ch.topic: schemas[ch.schema_id].name
            for ch in sorted(channels.values(), key=lambda c: c.topic)
            if ch.schema_id in schemas
        },
        decode_errors=sum(decode_errors.values()),
        vehicles=dict(sorted(vehicles.items())),
        link_events=link_events,
        counters=counters,
        first_log_time=first_log,
        last_log_time=last_log,
        radio={v: RadioSeries.from_rows(v, r) for v, r in sorted(radio_rows.items())},
        handovers=sorted(handovers, key=lambda h: (h.t, h.vehicle)),
        links_config=links_config,
        link_radios=_link_radios(links_config, problems),
        run_json=read_run_json(p.parent, attachments),
    )


def read_run_json(folder: Path, attachments: dict[str, bytes]) -> dict[str, Any]:
    """The run's run.json: the folder's copy, else the one attached to run.mcap (so a report
    rebuilt from the recording alone, anywhere, shows the same); {} without either."""
    try:
        raw = (folder / RUN_FILE).read_bytes()
    except OSError:
        raw = attachments.get(RUN_FILE, b"")
    try:
        out = json.loads(raw.decode("utf-8", "replace")) if raw else {}
    except ValueError:
        return {}
    return out if isinstance(out, dict) else {}


def _link_radios(
    config: dict[str, Any] | None, problems: list[str]
) -> dict[tuple[str, str], Radio]:
    """The radio of each link direction in links.json's starting `profiles`, rebuilt with
    `Radio.from_dict` (how `LinkProfile.from_dict` rebuilds it), not the whole profile: a
    profile field another version spells differently must not cost the report the radio. A
    radio that does not rebuild (a field of another version) is left out, with a problem."""
    out: dict[tuple[str, str], Radio] = {}
    links = (config or {}).get("links")
    if not isinstance(links, dict):
        return out
    for link, entry in sorted(links.items()):
        profiles = entry.get("profiles") if isinstance(entry, dict) else None
        for direction in DIRECTIONS:
            profile = profiles.get(direction) if isinstance(profiles, dict) else None
            radio = profile.get("radio") if isinstance(profile, dict) else None
            if not isinstance(radio, dict):
                continue  # a wired link, or a direction without an air interface
            try:
                out[(str(link), direction)] = Radio.from_dict(radio)
            except (TypeError, ValueError) as err:  # NrError is a ValueError
                problems.append(
                    f"{LINKS_CONFIG_FILE}: the {direction} radio of {link} does not rebuild ({err})"
                )
    return out


#: Where the channel's steps are recorded: `/radio/<vehicle>` (`layout.radio_topic`).
RADIO_PREFIX = radio_topic("")


def _radio_row(msg: Any) -> tuple[Any, ...]:
    return (_stamp(msg), str(msg.cell), *(float(getattr(msg, f)) for f in RADIO_NUMBERS))


#: The type of each `HandoverRec` field, which `_handover` converts the message's value to.
_HANDOVER_TYPES = get_type_hints(HandoverRec)


def _handover(msg: Any) -> HandoverRec:
    """A Handover message as a `HandoverRec` (each field converted to the record's type)."""
    values = {
        f.name: _HANDOVER_TYPES[f.name](getattr(msg, f.name))
        for f in fields(HandoverRec)
        if f.name != "t"
    }
    return HandoverRec(t=_stamp(msg), **values)


def _unpack_named(metadata: dict[str, dict[str, str]], name: str) -> dict[str, Any]:
    rec = metadata.get(name)
    if rec is None:
        return {}
    return {k: _json_or_text(v) for k, v in rec.items()}


def _take(
    topic: str,
    msg: Any,
    log_t: float,
    rows: dict[tuple[str, str], list[tuple[int, float, float, float, float, float, float]]],
    vehicle: Callable[[str], VehicleData],
    link_events: list[LinkEventRec],
    counter_rows: dict[tuple[str, str], list[tuple[float, ...]]],
    counter_backend: dict[tuple[str, str], str],
) -> None:
    """File one decoded message where the report looks for it."""
    if topic == LINK_EVENTS_TOPIC:
        link_events.append(
            LinkEventRec(
                t=_stamp(msg),
                scheduled_s=float(msg.scheduled_s),
                lateness_s=float(msg.lateness_s),
                action=str(msg.action),
                target=str(msg.target),
                direction=str(msg.direction),
                changes=list(zip(list(msg.keys), list(msg.values), strict=False)),
            )
        )
        return
    if topic == LINK_COUNTERS_TOPIC:
        direction = "up" if str(msg.direction).startswith("up") else "down"
        key = (str(msg.link), direction)
        counter_backend[key] = str(msg.backend)
        counter_rows[key].append(
            (
                _stamp(msg),
                float(msg.bytes_in),
                float(msg.bytes_out),
                float(msg.packets_in),
                float(msg.packets_out),
                float(msg.packets_dropped),
            )
        )
        return
    parts = topic.strip("/").split("/")
    if len(parts) != 2 or parts[1] not in VEHICLE_TOPICS:
        return  # a topic the report does not use; it is still counted in `topics`
    vname, kind = parts
    if kind in ("gt", "vo", "dnn_answer", "pose"):
        # On `pose`, `method` names the estimator; the other topics are one series each.
        key = str(msg.method) if kind == "pose" else kind
        # `vo` also appears as a method on `pose`; the raw sensor topic keeps its own name.
        key = "vo_raw" if kind == "vo" else key
        rows[(vname, key)].append(
            (
                int(msg.frame_id),
                _stamp(msg),
                float(msg.x),
                float(msg.y),
                float(msg.yaw),
                float(msg.latency_s),
                log_t,
            )
        )
    elif kind == "split_decision":
        vehicle(vname).decisions.append(
            Decision(
                t=_stamp(msg),
                log_time=log_t,
                frame_id=int(msg.frame_id),
                chosen=str(msg.chosen),
                chosen_index=int(msg.chosen_index),
                rule=str(msg.rule),
                arm_names=[str(a) for a in msg.arm_names],
                last_latency_s=float(msg.last_latency_s),
                plays=int(msg.plays),
                plays_total=int(msg.plays_total),
            )
        )
    elif kind == "detector":
        vehicle(vname).detector.append(
            DetectorUpdate(
                t=_stamp(msg),
                arm=str(msg.arm),
                kl=float(msg.kl),
                threshold=float(msg.threshold),
                consecutive=int(msg.consecutive),
                required=int(msg.required),
                reset=bool(msg.reset),
                at_play=int(msg.at_play),
            )
        )
    elif kind == "inference":
        vehicle(vname).inference.append(
            Inference(
                t=_stamp(msg),
                log_time=log_t,
                frame_id=int(msg.frame_id),
                split=str(msg.split),
                split_index=int(msg.split_index),
                payload_bytes=int(msg.payload_bytes),
                head_s=float(msg.head_s),
                edge_compute_s=float(msg.edge_compute_s),
                latency_s=float(msg.latency_s),
                ok=bool(msg.ok),
                timed_out=bool(msg.timed_out),
                error=str(msg.error),
            )
        )


__all__ = [
    "CounterSeries",
    "Decision",
    "DetectorUpdate",
    "HandoverRec",
    "Inference",
    "LinkEventRec",
    "PoseTrack",
    "ReportInputError",
    "RunData",
    "VehicleData",
    "read_run",
]
