"""The pure half of recording other processes' topics (`nodes.recording.topics`), without ROS:
which topics a recorder takes, the QoS it asks for, the messages naming what to install, the
stats it keeps and what a probe that heard nothing says. (The recorder and the probe running
against real publishers: tests/test_topic_recorder_ros.py.)"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from nodes.recording.topics import (
    BEST_EFFORT,
    RELIABLE,
    TRANSIENT_LOCAL,
    VOLATILE,
    QosChoice,
    RecordingStats,
    TopicSelectionError,
    TopicSelector,
    UnknownTypeError,
    adapted_qos,
    check_node_name,
    definition_missing,
    normalize_topic,
    package_missing,
    probe_timeout_message,
    split_type_name,
    type_missing,
    wheel_name,
)

# ---- which topics -----------------------------------------------------------------------------


def test_an_exact_topic_matches_only_itself_and_is_fully_qualified() -> None:
    sel = TopicSelector.parse(["/chatter", "camera/image"])
    assert sel.matches("/chatter") and sel.matches("/camera/image")
    assert not sel.matches("/chatter2") and not sel.matches("/ns/chatter")
    assert sel.to_dict() == {"topics": ["/camera/image", "/chatter"], "regex": []}


def test_a_regex_is_searched_in_the_full_name() -> None:
    sel = TopicSelector.parse(regexes=["^/chat", "image$"])
    assert sel.matches("/chatter") and sel.matches("/chat")
    assert not sel.matches("/ns/chatter")  # anchored at the start of the full name
    assert sel.matches("/av1/camera/image") and not sel.matches("/av1/image/info")
    # search, not match: an unanchored pattern is found anywhere
    assert TopicSelector.parse(regexes=["camera"]).matches("/av1/camera/info")


def test_topics_and_regexes_combine() -> None:
    sel = TopicSelector.parse(["/tf"], ["^/av[0-9]+/pose$"])
    assert [t for t in ("/tf", "/tf_static", "/av12/pose", "/av1/pose2") if sel.matches(t)] == [
        "/tf",
        "/av12/pose",
    ]


@pytest.mark.parametrize(
    ("topics", "regexes", "says"),
    [
        ([], [], "give at least one --topic or --regex"),
        ([], ["("], "--regex '(' is not a regular expression"),
        (["/a b"], [], "not a ROS topic name: '/a b'"),
        (["/"], [], "not a ROS topic name: '/'"),
        ([""], [], "not a ROS topic name: ''"),
    ],
)
def test_a_bad_selection_is_one_clear_error(
    topics: list[str], regexes: list[str], says: str
) -> None:
    with pytest.raises(TopicSelectionError) as exc:
        TopicSelector.parse(topics, regexes)
    assert says in str(exc.value)
    assert isinstance(exc.value, ValueError)  # run_main's "bad setting" family


def test_normalize_topic_and_node_names() -> None:
    assert normalize_topic(" chatter ") == "/chatter"
    assert normalize_topic("/a/b") == "/a/b"
    assert check_node_name("topic_recorder_2") == "topic_recorder_2"
    for bad in ("2rec", "rec-1", "", "a/b"):
        with pytest.raises(TopicSelectionError, match="node name"):
            check_node_name(bad)


# ---- with what QoS ----------------------------------------------------------------------------

R_V = QosChoice(RELIABLE, VOLATILE)
R_T = QosChoice(RELIABLE, TRANSIENT_LOCAL)
B_V = QosChoice(BEST_EFFORT, VOLATILE)
B_T = QosChoice(BEST_EFFORT, TRANSIENT_LOCAL)


@pytest.mark.parametrize(
    ("pubs", "chosen"),
    [
        ([], B_V),  # nothing known yet: what matches anyone
        ([R_V], R_V),
        ([R_T], R_T),  # a latched topic: a late recorder still gets the last message
        ([B_V], B_V),
        ([R_V, R_V], R_V),
        ([R_V, B_V], B_V),  # one best-effort publisher: reliable would not match it
        ([R_T, R_V], R_V),
        ([R_T, B_T], B_T),
    ],
)
def test_the_subscription_is_the_strongest_qos_every_publisher_offers(
    pubs: list[QosChoice], chosen: QosChoice
) -> None:
    got = adapted_qos(pubs)
    assert got == chosen
    assert all(got.receives_from(p) for p in pubs)


def test_receives_from_is_ddss_request_offered_rule() -> None:
    every = [R_V, R_T, B_V, B_T]
    assert all(B_V.receives_from(p) for p in every)
    assert [p for p in every if R_V.receives_from(p)] == [R_V, R_T]
    assert [p for p in every if B_T.receives_from(p)] == [R_T, B_T]
    assert [p for p in every if R_T.receives_from(p)] == [R_T]
    assert R_T.to_dict() == {"reliability": "reliable", "durability": "transient_local"}


# ---- which types ------------------------------------------------------------------------------


def test_the_wheel_of_a_ros_package() -> None:
    assert wheel_name("std_msgs") == "ros-jazzy-std-msgs"
    assert wheel_name("sensor_msgs_py") == "ros-jazzy-sensor-msgs-py"
    assert wheel_name("tf2_msgs", distro="kilted") == "ros-kilted-tf2-msgs"


def test_the_missing_package_message_names_the_wheel() -> None:
    assert package_missing("std_msgs/msg/String") == (
        "std_msgs/msg/String: package std_msgs is not installed in this interpreter; "
        "pip install ros-jazzy-std-msgs"
    )
    assert package_missing("my_robot_msgs/msg/Wheel", "libfoo.so: cannot open") == (
        "my_robot_msgs/msg/Wheel: package my_robot_msgs is not installed in this interpreter "
        "(libfoo.so: cannot open); pip install ros-jazzy-my-robot-msgs"
    )


def test_a_missing_type_or_definition_says_which_and_what_to_install() -> None:
    assert type_missing("std_msgs/msg/Nope") == (
        "std_msgs/msg/Nope: package std_msgs is installed but has no message Nope (another "
        "version of it?); pip install --upgrade ros-jazzy-std-msgs"
    )
    text = definition_missing("nav_msgs/msg/Odometry", "no definition of nav_msgs/msg/Odometry")
    assert text.startswith("nav_msgs/msg/Odometry: package nav_msgs imports but its definition")
    assert (
        "nav_msgs/msg/Odometry.msg" in text and "(no definition of nav_msgs/msg/Odometry)" in text
    )
    assert text.endswith("pip install --force-reinstall ros-jazzy-nav-msgs")


@pytest.mark.parametrize(
    ("name", "says"),
    [
        (
            "example_interfaces/action/Fibonacci_FeedbackMessage",
            "not the hidden topics of an action",
        ),
        ("example_interfaces/srv/AddTwoInts_Event", "not the hidden topics of a service"),
        ("std_msgs/String", "not a ROS message type name"),
        ("std_msgs/msg/", "not a ROS message type name"),
        ("a/msg/B/C", "not a ROS message type name"),
    ],
)
def test_only_message_types_are_recordable(name: str, says: str) -> None:
    with pytest.raises(UnknownTypeError) as exc:
        split_type_name(name)
    assert str(exc.value).startswith(f"{name}: ") and says in str(exc.value)


def test_split_type_name() -> None:
    assert split_type_name("geometry_msgs/msg/PoseStamped") == ("geometry_msgs", "PoseStamped")


# ---- what was recorded ------------------------------------------------------------------------


def test_stats_count_messages_bytes_and_receive_times_per_topic() -> None:
    stats = RecordingStats()
    stats.subscribed("/chatter", "std_msgs/msg/String", R_V)
    stats.subscribed("/odom", "nav_msgs/msg/Odometry", B_V)
    for i, size in enumerate((12, 13, 14)):
        stats.message("/chatter", size, 1_700_000_000_000_000_000 + i * 100_000_000)
    stats.subscribed("/chatter", "std_msgs/msg/String", B_V)  # again, weaker, for a new pub
    out = stats.to_dict()
    assert out["messages"] == 3 and out["bytes"] == 39
    assert out["topics"]["/chatter"] == {
        "type": "std_msgs/msg/String",
        "messages": 3,
        "bytes": 39,
        "first_time": 1_700_000_000.0,
        "last_time": 1_700_000_000.2,
        "qos": {"reliability": "best_effort", "durability": "volatile"},
        "subscriptions": 2,
    }
    assert out["topics"]["/odom"]["messages"] == 0
    assert out["topics"]["/odom"]["first_time"] is None
    assert out["type_errors"] == 0 and out["unknown_types"] == []
    json.dumps(out, allow_nan=False)  # what write_stats writes


def test_an_unknown_type_is_counted_once_with_its_error() -> None:
    stats = RecordingStats()
    error = package_missing("foo_msgs/msg/Bar")
    assert stats.failed("/bar", "foo_msgs/msg/Bar", error)  # first time: the caller logs it
    assert not stats.failed("/bar", "foo_msgs/msg/Bar", error)  # every later poll: silent
    assert stats.known_failure("/bar", "foo_msgs/msg/Bar")
    assert not stats.known_failure("/bar", "foo_msgs/msg/Baz")
    assert stats.failed("/baz", "foo_msgs/msg/Bar", error)  # another topic: its own entry
    out = stats.to_dict()
    assert out["type_errors"] == 2
    assert out["unknown_types"][0] == {"topic": "/bar", "type": "foo_msgs/msg/Bar", "error": error}
    assert out["topics"] == {} and out["messages"] == 0


# ---- what a probe says ------------------------------------------------------------------------


def test_a_probe_that_heard_nothing_says_why() -> None:
    never = probe_timeout_message("/x", 2.0, seen=False, publishers=0)
    assert never.startswith("no message on /x within 2 s: the topic never appeared")
    subs_only = probe_timeout_message("/x", 0.5, seen=True, publishers=0)
    assert "within 0.5 s" in subs_only and "never had a publisher" in subs_only
    silent = probe_timeout_message("/x", 20, seen=True, publishers=2, types=["std_msgs/msg/String"])
    assert "seen with 2 publisher(s) of std_msgs/msg/String" in silent
    assert "none published a message" in silent


def test_the_pure_half_imports_no_ros() -> None:
    code = (
        "import sys, nodes.recording.topics; "
        "print([m for m in sys.modules if m.split('.')[0] in ('rclpy', 'nodes') "
        "and (m.startswith('rclpy') or m.startswith('nodes.ros'))])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
