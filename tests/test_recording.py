"""Recording to MCAP without ROS or root: schema texts, part files, the merge into run.mcap
(order, compression, summary statistics, metadata, attachments), a part cut by a kill, and
decoding the result with two independent readers (mcap_ros2 and rosbags' AnyReader).

Messages are encoded with rosbags from the same schema texts, so these tests need neither
rclpy nor the built interfaces; `tests/test_recording_root.py` records real nodes.
"""

from __future__ import annotations

import json
import math
import random
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap_ros2._dynamic import generate_dynamic
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from nodes.recording import RecordingError, layout, parts, schemas
from nodes.recording import merge as mrg
from testbed import recording as rec

REPO = Path(__file__).resolve().parents[1]
OWN_MSGS = sorted(p.stem for p in (REPO / "nodes/edgeloc_interfaces/msg").glob("*.msg"))
TYPES = [f"edgeloc_interfaces/msg/{name}" for name in OWN_MSGS] + [
    "sensor_msgs/msg/Image",
    "std_msgs/msg/Header",
    "builtin_interfaces/msg/Time",
]


def _std_reason() -> str | None:
    try:
        schemas.find_msg_file("sensor_msgs/msg/Image")
    except RecordingError as err:
        return f"ROS message definitions not installed (`make setup`): {err}"
    return None


needs_std = pytest.mark.skipif(_std_reason() is not None, reason=str(_std_reason()))


# ---- schema texts ----------------------------------------------------------------------------


def test_msg_dependencies_reads_fields_arrays_bounds_and_constants() -> None:
    text = (
        "# a comment naming geometry_msgs/Pose\n"
        "Header header            # short form of std_msgs/Header\n"
        "builtin_interfaces/Time stamp\n"
        "Other[] local            # same package\n"
        "geometry_msgs/Point[<=3] pts\n"
        "string<=10 name\n"
        "uint8[16] raw\n"
        "int32 LIMIT=5\n"
        "float64 x 0.5\n"
    )
    assert schemas.msg_dependencies(text, "pkg") == [
        "std_msgs/msg/Header",
        "builtin_interfaces/msg/Time",
        "pkg/msg/Other",
        "geometry_msgs/msg/Point",
    ]


def test_full_type_name_accepts_both_spellings_and_refuses_others() -> None:
    assert schemas.full_type_name("a/B") == "a/msg/B"
    assert schemas.full_type_name("a/msg/B") == "a/msg/B"
    with pytest.raises(RecordingError, match="pkg/msg/Type"):
        schemas.full_type_name("B")


def test_every_interface_message_is_covered() -> None:
    # A message added to the package without a schema test would slip through.
    assert "InferenceResult" in OWN_MSGS and "LinkCounters" in OWN_MSGS and len(OWN_MSGS) >= 6


@needs_std
@pytest.mark.parametrize("type_name", TYPES)
def test_schema_text_is_complete_and_both_readers_parse_it(type_name: str) -> None:
    text = schemas.schema_text(type_name)
    own = schemas.find_msg_file(type_name).read_text().rstrip("\n")
    assert text.startswith(own)
    sections = text.split(schemas.SEPARATOR + "\n")
    names = [s.splitlines()[0].removeprefix("MSG: ") for s in sections[1:]]
    assert len(names) == len(set(names)), names  # each dependency once
    # Every type used anywhere in the text is defined in it (transitively complete).
    used = set(schemas.msg_dependencies(own, type_name.split("/")[0]))
    for section in sections[1:]:
        head, body = section.split("\n", 1)
        used |= set(schemas.msg_dependencies(body, head.removeprefix("MSG: ").split("/")[0]))
    assert used <= set(names), used - set(names)
    assert type_name in get_types_from_msg(text, type_name)
    assert type_name in generate_dynamic(type_name, text)


def test_missing_definition_names_the_type_and_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"nope/msg/Gone.*" + str(tmp_path)):
        schemas.schema_text("nope/msg/Gone", search=[tmp_path])


# ---- encoding helpers (rosbags: independent of rclpy) ----------------------------------------


@pytest.fixture(scope="module")
def store() -> Any:
    if _std_reason():
        pytest.skip(str(_std_reason()))
    ts = get_typestore(Stores.EMPTY)
    for t in TYPES:
        ts.register(get_types_from_msg(schemas.schema_text(t), t))
    return ts


def _time(store: Any, t: float) -> Any:
    sec = math.floor(t)
    return store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int((t - sec) * 1e9))


def pose(store: Any, t: float, frame: int, method: str = "vo") -> Any:
    return store.types["edgeloc_interfaces/msg/PoseEstimate"](
        stamp=_time(store, t),
        vehicle="av1",
        method=method,
        x=float(frame),
        y=-float(frame),
        yaw=0.25,
        latency_s=math.nan,
        frame_id=frame,
        entropy_nats=math.nan,
    )


def counters(store: Any, t: float, n: int) -> Any:
    row = {
        "link": "av1-gnb1",
        "direction": "up",
        "packets_in": n,
        "bytes_in": 1500 * n,
        "packets_out": n,
        "bytes_out": 1500 * n,
        "packets_dropped": 0,
        "bytes_dropped": 0,
        "queue_packets": 3,
    }
    return store.types["edgeloc_interfaces/msg/LinkCounters"](
        stamp=_time(store, t), backend="userspace", **row
    )


POSE = "edgeloc_interfaces/msg/PoseEstimate"
COUNTERS = "edgeloc_interfaces/msg/LinkCounters"


def _write_parts(store: Any, folder: Path, n: int = 200) -> dict[str, list[tuple[int, bytes]]]:
    """Two parts with interleaved, shuffled-between-parts log times; returns what was sent
    per topic as (log time, CDR bytes)."""
    sent: dict[str, list[tuple[int, bytes]]] = {"/av1/vo": [], "/links/counters": []}
    a = parts.PartWriter(layout.part_path(folder, "av1.sensor"), chunk_bytes=2048)
    b = parts.PartWriter(layout.part_path(folder, "orchestrator"), compression="zstd")
    base = 1_700_000_000_000_000_000
    for i in range(n):
        t = base + i * 50_000_000
        data = bytes(store.serialize_cdr(pose(store, t / 1e9, i), POSE))
        a.write("/av1/vo", POSE, data, t)
        sent["/av1/vo"].append((t, data))
        if i % 5 == 0:
            tc = t - 10_000_000  # a little earlier than the pose it follows in the queue
            cdata = bytes(store.serialize_cdr(counters(store, tc / 1e9, i), COUNTERS))
            b.write("/links/counters", COUNTERS, cdata, tc)
            sent["/links/counters"].append((tc, cdata))
    a.close()
    b.close()
    return sent


# ---- parts and merge -------------------------------------------------------------------------


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_merge_orders_by_log_time_with_summary_metadata_and_attachments(
    store: Any, tmp_path: Path, compression: str
) -> None:
    sent = _write_parts(store, tmp_path)
    parts = sorted(layout.parts_dir(tmp_path).glob("*.mcap"))
    out = tmp_path / "run.mcap"
    meta = {"edgeloc.run": {"run_id": "abc123", "seed": "7"}}
    attachment = mrg.Attachment("scenario.yaml", "application/yaml", b"name: x\n", 5)
    report = mrg.merge(parts, out, compression, metadata=meta, attachments=[attachment])
    assert report.counts == {t: len(v) for t, v in sent.items()}
    assert all(p["complete"] for p in report.parts.values())

    with open(out, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        stats = summary.statistics
        assert stats.message_count == sum(len(v) for v in sent.values())
        by_topic = {
            summary.channels[cid].topic: n for cid, n in stats.channel_message_counts.items()
        }
        assert by_topic == report.counts
        assert stats.message_start_time == min(t for v in sent.values() for t, _ in v)
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {s.name for s in summary.schemas.values()} == {POSE, COUNTERS}
        assert summary.chunk_indexes
        want = "" if compression == "none" else compression
        assert {c.compression for c in summary.chunk_indexes} == {want}
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=False)]
        assert times == sorted(times) and len(times) == stats.message_count
        got = {(m.log_time, bytes(m.data)) for _, _, m in reader.iter_messages()}
        assert got == {x for v in sent.values() for x in v}
        metas = {m.name: m.metadata for m in reader.iter_metadata()}
        assert metas == meta
        atts = list(reader.iter_attachments())
        assert [(a.name, a.media_type, a.data) for a in atts] == [
            ("scenario.yaml", "application/yaml", b"name: x\n")
        ]


def test_both_readers_decode_every_message(store: Any, tmp_path: Path) -> None:
    sent = _write_parts(store, tmp_path, n=60)
    out = tmp_path / "run.mcap"
    mrg.merge(sorted(layout.parts_dir(tmp_path).glob("*.mcap")), out, "zstd")

    decoded: dict[str, list[Any]] = {}
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(msg)
    assert {t: len(v) for t, v in decoded.items()} == {t: len(v) for t, v in sent.items()}
    assert [m.frame_id for m in decoded["/av1/vo"]] == list(range(60))
    assert decoded["/links/counters"][1].bytes_in == 1500 * 5

    with AnyReader([out]) as reader:
        seen: dict[str, int] = {}
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
            if conn.topic == "/av1/vo":
                assert msg.vehicle == "av1" and math.isnan(msg.latency_s)
        assert seen == {t: len(v) for t, v in sent.items()}
        assert {c.msgtype for c in reader.connections} == {POSE, COUNTERS}


def test_a_part_cut_by_a_kill_merges_up_to_its_last_chunk(store: Any, tmp_path: Path) -> None:
    path = layout.part_path(tmp_path, "av1.fusion")
    # Big chunks, short flush interval: each quiet pause ends one chunk.
    part = parts.PartWriter(path, chunk_bytes=1 << 20, flush_s=0.1)
    data = store.serialize_cdr(pose(store, 1.0, 1), POSE)
    for batch in range(3):
        for i in range(10):
            part.write("/av1/pose", POSE, data, (batch * 10 + i + 1) * 1000)
        time.sleep(0.5)
    part.close()
    full = path.read_bytes()
    whole = parts.read_part(path)
    assert whole.complete and len(whole.messages) == 30 and not whole.problem
    # Cut the file inside its third chunk, as a SIGKILL during that write would.
    offsets = _chunk_offsets(path)
    assert len(offsets) == 3
    path.write_bytes(full[: offsets[2] + 40])
    torn = parts.read_part(path)
    assert not torn.complete and torn.problem
    assert len(torn.messages) == 20
    report = mrg.merge([path], tmp_path / "run.mcap", "zstd")
    assert report.counts == {"/av1/pose": 20}
    assert not report.parts["av1.fusion.mcap"]["complete"]
    with AnyReader([tmp_path / "run.mcap"]) as reader:
        assert sum(1 for _ in reader.messages()) == 20


def _chunk_offsets(path: Path) -> list[int]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted(c.chunk_start_offset for c in summary.chunk_indexes)


def test_part_writer_flushes_a_quiet_topic_within_its_interval(store: Any, tmp_path: Path) -> None:
    path = layout.part_path(tmp_path, "gnb1.link_events")
    part = parts.PartWriter(path, flush_s=0.2)
    try:
        part.write("/av1/vo", POSE, store.serialize_cdr(pose(store, 1.0, 1), POSE))
        time.sleep(0.6)
        # The writer is still open (as when a node is SIGKILLed now), yet the message is there.
        got = parts.read_part(path)
        assert not got.complete and len(got.messages) == 1
        assert got.channels[got.messages[0].channel_id].topic == "/av1/vo"
    finally:
        part.close()
    assert part.counts == {"/av1/vo": 1}


def test_a_writer_failure_is_reported_not_swallowed(tmp_path: Path) -> None:
    part = parts.PartWriter(tmp_path / "x.mcap", search=[tmp_path])
    part.write("/t", "nope/msg/Gone", b"\x00\x01\x00\x00")
    with pytest.raises(RecordingError, match="nope/msg/Gone"):
        part.close()
    with pytest.raises(RecordingError, match="failed"):
        part.write("/t", "nope/msg/Gone", b"")


def test_bad_compression_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="zstd, lz4, none"):
        mrg.merge([], tmp_path / "run.mcap", "gzip")


def test_counter_rows_from_a_relay_reply() -> None:
    reply = {
        "uplink": {
            "total": {
                "packets_in": 10,
                "bytes_in": 1000,
                "packets_out": 8,
                "bytes_out": 800,
                "dropped_packets": {"loss": 1, "queue_full": 1},
                "dropped_bytes": {"loss": 100, "queue_full": 100},
            },
            "queued": 4,
        },
        "downlink": {"total": {"packets_in": 2}, "queued": 0},
    }
    up, down = rec.counter_rows("av1-gnb1", reply)
    assert up["direction"] == "up" and up["packets_dropped"] == 2 and up["bytes_dropped"] == 200
    assert up["queue_packets"] == 4 and down["direction"] == "down" and down["packets_in"] == 2


# ---- finalise a run folder -------------------------------------------------------------------


def _fake_run(store: Any, folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    trace = folder.parent / "uplink.csv"
    trace.write_text("0,10\n1,5\n")
    rec.write_manifest(
        folder,
        {
            "run_id": "a1b2c3",
            "scenario": "unit",
            "seed": 7,
            "link_backend": "userspace (auto: no sch_netem)",
            "started": time.time() - 3,
            "compression": "lz4",
            "versions": {"testbed_version": "0.1.0", "python": "3.11"},
            "host": {"sch_netem": False},
            "namespaces": {"av1": "el-a1b2c3-av1", "gnb1": "el-a1b2c3-gnb1"},
            "traces": [str(trace)],
            "timeline_events": 2,
        },
    )
    (folder / "scenario.yaml").write_text("name: unit\n")
    (folder / "events.jsonl").write_text(
        json.dumps({"kind": "shape", "lateness_s": 0.004, "error": None})
        + "\n"
        + json.dumps({"kind": "set", "lateness_s": 0.002, "error": None})
        + "\n"
    )
    (folder / "linktest.json").write_text(json.dumps({"ok": True, "seconds": 9.5}))
    (folder / "links.json").write_text(json.dumps({"backend": "userspace", "links": {}}))
    (folder / "nodes").mkdir()
    (folder / "nodes" / "av1.sensor.json").write_text('{"frames": 5, "lateness": NaN}')
    (folder / layout.NODE_CONFIG_FILE).write_text(json.dumps({"seed": 7}))
    (folder / "logs").mkdir()
    (folder / "logs" / "av1.sensor.log").write_text("\n".join(f"line {i}" for i in range(30)))
    (folder / "logs" / "gnb1.link_events.log").write_text("ok\n")
    part = parts.PartWriter(layout.part_path(folder, "av1.sensor"))
    for i in range(5):
        part.write("/av1/vo", POSE, store.serialize_cdr(pose(store, 1.0 + i, i), POSE))
    part.close()


def test_finalise_writes_run_metadata_and_attachments_and_removes_parts(
    store: Any, tmp_path: Path
) -> None:
    folder = tmp_path / "runs" / "a1b2c3"
    _fake_run(store, folder)
    nodes = {
        "processes": {
            "av1.sensor": {"exit_code": -9, "stats": {}},
            "gnb1.link_events": {"exit_code": 0, "stats": {"published": 2}},
        }
    }
    report = rec.finalise(folder, "failed: node av1.sensor exited with -9", nodes=nodes)
    assert report.counts == {"/av1/vo": 5}
    assert not layout.parts_dir(folder).exists()
    with open(folder / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        assert {c.compression for c in summary.chunk_indexes} == {"lz4"}
        metas = {m.name: m.metadata for m in reader.iter_metadata()}
        run = metas["edgeloc.run"]
        assert run["run_id"] == "a1b2c3" and run["seed"] == "7" and run["scenario"] == "unit"
        assert run["status"].startswith("failed: node av1.sensor")
        assert run["link_backend"].startswith("userspace")
        assert float(run["duration_s"]) >= 3 and run["started"].endswith("+00:00")
        assert json.loads(run["host"]) == {"sch_netem": False}
        sensor = json.loads(metas["edgeloc.nodes"]["av1.sensor"])
        assert sensor["namespace"] == "el-a1b2c3-av1" and sensor["exit_code"] == -9
        assert sensor["stats"] == {"frames": 5, "lateness": None}  # its file; NaN -> null
        assert "NaN" not in metas["edgeloc.nodes"]["av1.sensor"]
        assert sensor["log_tail"] == [f"line {i}" for i in range(10, 30)]
        events = json.loads(metas["edgeloc.nodes"]["gnb1.link_events"])
        assert events["exit_code"] == 0 and "log_tail" not in events
        timeline = metas["edgeloc.timeline"]
        assert timeline["applied"] == "2" and timeline["events"] == "2"
        assert json.loads(timeline["lateness"])["max_ms"] == pytest.approx(4.0)
        assert metas["edgeloc.linktest"]["ok"] == "true"
        names = {a.name for a in reader.iter_attachments()}
        assert names == {
            "scenario.yaml",
            "events.jsonl",
            "linktest.json",
            "links.json",
            "nodes/config.json",
            "traces/uplink.csv",
        }
        decoded = [m.frame_id for _, _, _, m in reader.iter_decoded_messages()]
        assert decoded == [0, 1, 2, 3, 4]


def test_finalise_keeps_the_parts_when_the_merge_fails(store: Any, tmp_path: Path) -> None:
    folder = tmp_path / "r"
    _fake_run(store, folder)
    # A part written against another build of the interfaces: PoseEstimate differs.
    other = tmp_path / "other"
    (other / "edgeloc_interfaces" / "msg").mkdir(parents=True)
    (other / "edgeloc_interfaces" / "msg" / "PoseEstimate.msg").write_text("int8 x\n")
    bad = parts.PartWriter(layout.part_path(folder, "av1.fusion"), search=[other])
    bad.write("/av1/pose", POSE, b"\x00\x01\x00\x00\x05")
    bad.close()
    with pytest.raises(RecordingError, match="different definition"):
        rec.finalise(folder, "ok")
    assert (layout.parts_dir(folder) / "av1.fusion.mcap").is_file()
    assert not (folder / "run.mcap").exists()


def test_merge_of_many_random_parts_is_a_sorted_union(store: Any, tmp_path: Path) -> None:
    rng = random.Random(3)
    data = store.serialize_cdr(pose(store, 1.0, 1), POSE)
    want = []
    for p in range(4):
        part = parts.PartWriter(layout.part_path(tmp_path, f"p{p}"), chunk_bytes=512)
        times = sorted(rng.randrange(10**6) for _ in range(50))
        for t in times:
            part.write(f"/v{p}/vo", POSE, data, t)
            want.append(t)
        part.close()
    report = mrg.merge(sorted(layout.parts_dir(tmp_path).glob("*.mcap")), tmp_path / "m.mcap")
    assert report.messages == 200
    with open(tmp_path / "m.mcap", "rb") as f:
        got = [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]
    assert got == sorted(want)


def test_detector_messages_follow_every_update_and_flag_the_reset() -> None:
    """What /<vehicle>/detector records: one message per detector update, the streak of
    updates above threshold as the detector counts it, `reset` on the confirming update."""
    pytest.importorskip("edgeloc_interfaces.msg", reason="interfaces not built (`make setup`)")
    from nodes.edgeloc.detector import KLChangeDetector
    from nodes.ros.inference_request import detector_msg

    det = KLChangeDetector(window=2, threshold=1.0, consecutive=2)
    streaks: dict[str, int] = {}
    msgs = []
    for cost in (1.0, 1.0, 1.0, 1.0, 5.0, 5.0, 1.0):
        event = det.update("conv3", cost)
        msgs.append(detector_msg("av1", det, "conv3", event, streaks, 1.0))
    assert [m.at_play for m in msgs] == [1, 2, 3, 4, 5, 6, 7]
    assert [math.isnan(m.kl) for m in msgs] == [True, True, True, False, False, False, True]
    assert [m.consecutive for m in msgs] == [0, 0, 0, 0, 1, 2, 0]
    assert [m.reset for m in msgs] == [False] * 5 + [True, False]
    assert msgs[5].kl > 1.0 and msgs[5].required == 2 and msgs[5].threshold == 1.0


def test_links_json_of_a_tc_run_lists_profiles_and_the_tc_commands() -> None:
    """links.json (attached to run.mcap) for the tc backend: per link and direction the
    profile, plus the tc commands that realise them (rendered by a dry-run controller)."""
    import dataclasses

    from testbed.recording import links_config
    from testbed.topology import build, example_scenario

    scenario = example_scenario()
    scenario = dataclasses.replace(
        scenario, links=dataclasses.replace(scenario.links, backend="tc")
    )
    net = build(scenario, dry_run=True)
    cfg = links_config(net, "tc (test)")
    assert set(cfg["links"]) == {"av1-gnb1", "gnb1-core1"}
    assert set(cfg["links"]["av1-gnb1"]["profiles"]) == {"uplink", "downlink"}
    assert any(line.startswith("tc -n ") and " htb " in line for line in cfg["tc_commands"])


def test_an_inference_node_with_no_answer_is_named() -> None:
    from testbed.run import unanswered

    nodes = {
        "processes": {
            "av1.inference": {"stats": {"requests": 780, "answers": 779}},
            "av2.inference": {"stats": {"requests": 0, "answers": 0}},
            "av3.inference": {"stats": {}},  # died before writing stats: reported elsewhere
            "av2.fusion": {"stats": {"answers": 0}},
        }
    }
    assert unanswered(nodes) == ["av2.inference"]
