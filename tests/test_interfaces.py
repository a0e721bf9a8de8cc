"""edgeloc_interfaces and the ROS environment of a run.

edgeloc_interfaces (tests marked `ros`): every message and the action's parts survive CDR
serialization, carry the fields the nodes rely on, and the installed .msg definitions describe
the bytes rclpy writes (checked with rosbags, an independent CDR reader: what an MCAP reader
will do with them). nodes.ros.env (pure): the environment and profile it writes."""

from __future__ import annotations

import array
import random
import re
import sys
from pathlib import Path
from typing import Any

import pytest

MSG_DIR = Path(__file__).resolve().parents[1] / "nodes" / "edgeloc_interfaces" / "msg"
#: Every message the package defines: its .msg files, so a new one is tested without a list.
MESSAGES = tuple(sorted(p.stem for p in MSG_DIR.glob("*.msg")))
ACTION_PARTS = ("Goal", "Result", "Feedback")

# The contract with the nodes and the recorder: field -> ROS type (as rosidl reports it).
EXPECTED_FIELDS: dict[str, dict[str, str]] = {
    "SplitDecision": {
        "stamp": "builtin_interfaces/Time", "vehicle": "string", "frame_id": "uint32",
        "chosen": "string", "chosen_index": "uint8", "rule": "string",
        "arm_names": "sequence<string>", "arm_n": "sequence<uint32>",
        "arm_mean": "sequence<double>", "arm_var": "sequence<double>",
        "arm_index": "sequence<double>", "last_latency_s": "double", "plays": "uint64",
        "plays_total": "uint64",
    },
    "DetectorEvent": {
        "stamp": "builtin_interfaces/Time", "vehicle": "string", "arm": "string",
        "kl": "double", "threshold": "double", "consecutive": "uint32", "required": "uint32",
        "reset": "boolean", "at_play": "uint64",
    },
    "LinkEvent": {
        "stamp": "builtin_interfaces/Time", "scheduled_s": "double", "lateness_s": "double",
        "action": "string", "target": "string", "direction": "string",
        "keys": "sequence<string>", "values": "sequence<string>",
    },
    "LinkCounters": {
        "stamp": "builtin_interfaces/Time", "link": "string", "direction": "string",
        "backend": "string", "packets_in": "uint64", "bytes_in": "uint64",
        "packets_out": "uint64", "bytes_out": "uint64", "packets_dropped": "uint64",
        "bytes_dropped": "uint64", "queue_packets": "uint32",
    },
    "PoseEstimate": {
        "stamp": "builtin_interfaces/Time", "vehicle": "string", "method": "string",
        "x": "double", "y": "double", "yaw": "double", "latency_s": "double",
        "frame_id": "uint32", "entropy_nats": "double",
    },
    "Goal": {
        "vehicle": "string", "frame_id": "uint32", "split_name": "string",
        "split_index": "uint8", "capture_stamp": "builtin_interfaces/Time", "codec": "string",
        "shape": "sequence<int32>", "dtype": "string", "payload": "sequence<uint8>",
    },
    "Result": {
        "ok": "boolean", "error": "string", "frame_id": "uint32", "split_index": "uint8",
        "pose": "geometry_msgs/PoseWithCovarianceStamped", "edge_compute_s": "double",
        "entropy_nats": "double", "edge_receive_stamp": "builtin_interfaces/Time",
        "edge_send_stamp": "builtin_interfaces/Time",
    },
    "Feedback": {"stage": "string"},
    "InferenceResult": {
        "stamp": "builtin_interfaces/Time", "vehicle": "string", "frame_id": "uint32",
        "split": "string", "split_index": "uint8", "payload_bytes": "uint64",
        "head_s": "double", "edge_compute_s": "double", "latency_s": "double",
        "ok": "boolean", "timed_out": "boolean", "error": "string", "edge": "string",
    },
    "RadioState": {
        "stamp": "builtin_interfaces/Time", "vehicle": "string", "cell": "string",
        "x": "double", "y": "double", "rsrp_dbm": "double", "sinr_db": "double",
        "cqi": "int32", "mcs": "int32", "bler": "double", "ul_sinr_db": "double",
        "ul_mcs": "int32", "ul_bler": "double",
    },
    "Handover": {
        "stamp": "builtin_interfaces/Time", "vehicle": "string", "source": "string",
        "target": "string", "scheduled_s": "double", "lateness_s": "double",
        "interruption_s": "double", "lossless": "boolean", "error": "string",
    },
    "TrafficSample": {
        "stamp": "builtin_interfaces/Time", "flow": "string", "kind": "string",
        "role": "string", "t": "double", "bytes": "uint64", "packets": "uint64",
        "rate_bps": "double", "goodput_bps": "double", "loss": "double",
        "delay_ms": "double", "rtt_ms": "double", "late": "uint64",
    },
}  # fmt: skip


def test_every_message_and_action_part_has_its_contract() -> None:
    assert len(MESSAGES) >= 9, MESSAGES  # the glob found the package's messages
    assert set(MESSAGES) | set(ACTION_PARTS) == set(EXPECTED_FIELDS)


_INT_RANGES = {
    "uint8": (0, 2**8 - 1), "uint16": (0, 2**16 - 1), "uint32": (0, 2**32 - 1),
    "uint64": (0, 2**64 - 1), "int8": (-(2**7), 2**7 - 1), "int16": (-(2**15), 2**15 - 1),
    "int32": (-(2**31), 2**31 - 1), "int64": (-(2**63), 2**63 - 1),
    "octet": (0, 255), "byte": (0, 255), "char": (0, 255),
}  # fmt: skip
_ARRAY_CODES = {"uint8": "B", "int32": "i", "uint32": "I", "double": "d", "float": "f"}


@pytest.fixture(scope="module")
def iface() -> Any:
    """The installed package (built once into this interpreter's prefix if needed)."""
    from nodes.ros.build import BuildError, ensure_built

    try:
        ensure_built()
    except BuildError as err:
        pytest.fail(f"edgeloc_interfaces could not be built: {err}")
    import edgeloc_interfaces.action
    import edgeloc_interfaces.msg

    return edgeloc_interfaces


def _types(iface: Any) -> dict[str, type]:
    found = {name: getattr(iface.msg, name) for name in MESSAGES}
    for part in ACTION_PARTS:
        found[part] = getattr(iface.action.SplitInference, part)
    return found


def _value(ros_type: str, rng: random.Random) -> Any:
    """A random value of `ros_type` (as in get_fields_and_field_types), extremes included."""
    seq = re.fullmatch(r"sequence<(.+?)(?:, \d+)?>", ros_type)
    fixed = re.fullmatch(r"(.+)\[(\d+)\]", ros_type)
    if seq or fixed:
        inner = (seq or fixed).group(1)  # type: ignore[union-attr]
        n = int(fixed.group(2)) if fixed else rng.randint(0, 5)
        items = [_value(inner, rng) for _ in range(n)]
        if seq and inner in _ARRAY_CODES:
            return array.array(_ARRAY_CODES[inner], items)
        return items
    if ros_type in _INT_RANGES:
        lo, hi = _INT_RANGES[ros_type]
        return rng.choice([lo, hi, rng.randint(lo, hi)])
    if ros_type in ("double", "float"):
        value = rng.choice([0.0, -1.5e-9, 123456.789, rng.uniform(-1e6, 1e6)])
        return float(array.array("f", [value])[0]) if ros_type == "float" else value
    if ros_type == "boolean":
        return rng.random() < 0.5
    if ros_type == "string":
        return rng.choice(["", "av1", "fp16-zlib", "layer3 ü", "x" * 300])
    return _message(_resolve(ros_type), rng)


def _resolve(ros_type: str) -> type:
    package, name = ros_type.split("/")
    module = __import__(f"{package}.msg", fromlist=[name])
    return getattr(module, name)


def _message(cls: type, rng: random.Random) -> Any:
    msg = cls()
    for field, ros_type in cls.get_fields_and_field_types().items():
        setattr(msg, field, _value(ros_type, rng))
    return msg


@pytest.mark.ros
def test_fields_are_the_contract(iface: Any) -> None:
    for name, cls in _types(iface).items():
        assert cls.get_fields_and_field_types() == EXPECTED_FIELDS[name], name


@pytest.mark.ros
@pytest.mark.parametrize("seed", range(5))
def test_every_type_round_trips_through_cdr(iface: Any, seed: int) -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    rng = random.Random(seed)
    for name, cls in _types(iface).items():
        msg = _message(cls, rng)
        data = serialize_message(msg)
        back = deserialize_message(data, cls)
        assert back == msg, name
        # (Bytes are not compared again: Fast CDR leaves alignment padding uninitialised, so
        # re-serialising an equal message may differ in those bytes.)


@pytest.mark.ros
def test_one_mebibyte_goal_round_trips(iface: Any) -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    goal_cls = iface.action.SplitInference.Goal
    blob = bytes(range(256)) * 4096
    goal = goal_cls(frame_id=7, split_name="layer2", split_index=2, codec="fp16-zlib")
    goal.shape = array.array("i", [1, 64, 64, 64])
    goal.payload = array.array("B", blob)
    data = serialize_message(goal)
    assert len(data) > len(blob)
    back = deserialize_message(data, goal_cls)
    assert bytes(back.payload) == blob
    assert list(back.shape) == [1, 64, 64, 64] and back.codec == "fp16-zlib"


def _share() -> Path:
    return Path(sys.prefix) / "share" / "edgeloc_interfaces"


def _definition_fields(text: str) -> list[str]:
    """Field names of a .msg definition, comments and blank lines ignored."""
    names = []
    for line in text.splitlines():
        code = line.split("#", 1)[0].strip()
        if code:
            names.append(code.split()[1])
    return names


@pytest.mark.ros
def test_installed_definitions_match_the_types(iface: Any) -> None:
    for name in MESSAGES:
        text = (_share() / "msg" / f"{name}.msg").read_text()
        assert _definition_fields(text) == list(EXPECTED_FIELDS[name]), name
    parts = (_share() / "action" / "SplitInference.action").read_text().split("\n---\n")
    assert len(parts) == 3
    for part, text in zip(ACTION_PARTS, parts, strict=True):
        assert _definition_fields(text) == list(EXPECTED_FIELDS[part]), part


@pytest.mark.ros
def test_definitions_decode_rclpy_bytes_independently(iface: Any) -> None:
    """rosbags, given only the installed .msg text, reads what rclpy serialized."""
    from rclpy.serialization import serialize_message
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for name in MESSAGES:
        text = (_share() / "msg" / f"{name}.msg").read_text()
        store.register(get_types_from_msg(text, f"edgeloc_interfaces/msg/{name}"))
    rng = random.Random(11)
    for name in MESSAGES:
        msg = _message(getattr(iface.msg, name), rng)
        decoded = store.deserialize_cdr(serialize_message(msg), f"edgeloc_interfaces/msg/{name}")
        for field in EXPECTED_FIELDS[name]:
            assert _plain(getattr(decoded, field)) == _plain(getattr(msg, field)), (name, field)


def _plain(value: Any) -> Any:
    """A field value as plain Python, whichever library made it."""
    if hasattr(value, "sec") and hasattr(value, "nanosec"):
        return (value.sec, value.nanosec)
    if isinstance(value, (str, bytes)):
        return value
    if hasattr(value, "__len__"):
        return [_plain(v) for v in value]
    return value.item() if hasattr(value, "item") else value


# ---- nodes.ros.env: pure, no ROS needed ----------------------------------------------------


def test_ros_env_sets_domain_peers_and_profile(tmp_path: Path) -> None:
    from nodes.ros.env import PROFILE_NAME, RMW, RosEnv

    base = {"PATH": "/usr/bin", "ROS_LOCALHOST_ONLY": "1", "ROS_STATIC_PEERS": "10.9.9.9"}
    env = RosEnv(tmp_path / "run", 42).environ(["10.200.0.2", "10.200.0.6", "10.200.0.2"], base)
    assert env["ROS_DOMAIN_ID"] == "42" and env["RMW_IMPLEMENTATION"] == RMW
    assert env["ROS_STATIC_PEERS"] == "10.200.0.2;10.200.0.6"  # ours replace inherited ones
    assert "ROS_LOCALHOST_ONLY" not in env and env["PATH"] == "/usr/bin"
    profile = Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"])
    assert profile == (tmp_path / "run" / PROFILE_NAME).resolve()
    text = profile.read_text()
    assert "<useBuiltinTransports>false</useBuiltinTransports>" in text  # no shared memory
    assert text.count(">4194304<") == 4  # send/receive on the transport and the participant
    quiet = RosEnv(tmp_path / "run", 42).environ(["10.200.0.2"], base, static_peers=False)
    assert "ROS_STATIC_PEERS" not in quiet


def test_ros_env_adds_the_prefix_for_apt_installs(tmp_path: Path) -> None:
    from nodes.ros.env import RosEnv

    env = RosEnv(tmp_path, 1, prefix=tmp_path / "venv").environ(
        base={"LD_LIBRARY_PATH": "/opt/ros/jazzy/lib"}
    )
    lib = str(tmp_path / "venv" / "lib")
    assert env["LD_LIBRARY_PATH"].split(":") == [lib, "/opt/ros/jazzy/lib"]
    assert env["AMENT_PREFIX_PATH"] == str(tmp_path / "venv")


@pytest.mark.parametrize(
    ("kwargs", "peers", "message"),
    [
        ({"domain_id": 102}, [], "0..101"),
        ({"domain_id": True}, [], "integer"),
        ({"domain_id": 1, "socket_buffer_bytes": 1000}, [], "socket buffer"),
        ({"domain_id": 1}, ["gnb1"], "not an IPv4 address"),
        ({"domain_id": 1}, ["fe80::1"], "not IPv4"),
        ({"domain_id": 1}, [f"10.0.0.{i}" for i in range(40)], "at most 32"),
    ],
)
def test_ros_env_refuses_bad_input(
    tmp_path: Path, kwargs: dict[str, Any], peers: list[str], message: str
) -> None:
    from nodes.ros.env import RosEnv, RosEnvError

    with pytest.raises(RosEnvError, match=re.escape(message)):
        RosEnv(tmp_path, **kwargs).environ(peers, base={})


def test_domain_id_for_run_ids() -> None:
    from nodes.ros.env import RosEnvError, domain_id_for

    ids = {domain_id_for(f"{i:06x}") for i in range(300)}
    assert ids == set(range(1, 101))
    with pytest.raises(RosEnvError, match="not hexadecimal"):
        domain_id_for("zz")


def test_fastdds_profile_is_xml_with_fast_reliable_repair() -> None:
    import xml.etree.ElementTree as ET

    from nodes.ros.env import HEARTBEAT_PERIOD_NS, fastdds_profile

    ns = {"d": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.fromstring(fastdds_profile())
    writer = root.find("d:profiles/d:data_writer", ns)
    assert writer is not None and writer.get("is_default_profile") == "true"
    period = writer.find("d:times/d:heartbeatPeriod", ns)
    assert period is not None
    seconds = (
        int(period.findtext("d:sec", namespaces=ns))
        + int(period.findtext("d:nanosec", namespaces=ns)) / 1e9
    )
    # a lost frame must be repaired about as fast as the latency model's 200 ms RTO assumes
    assert seconds == HEARTBEAT_PERIOD_NS / 1e9 <= 0.2
    assert root.find("d:profiles/d:participant/d:rtps/d:useBuiltinTransports", ns).text == "false"
