"""Recording topics that other processes publish: which topics, with what QoS, and what was seen.

The pure half of `nodes.ros.topic_recorder` and `nodes.ros.topic_probe` (no rclpy import, so
it is unit-tested without ROS):

- `TopicSelector`: the topics a recorder takes, by exact name (`--topic`) or by a regular
  expression searched in the full name (`--regex`);
- `QosChoice`: the reliability and durability a subscription asks for, chosen from those of
  the topic's publishers (`adapted_qos`) so that it receives from every one of them;
- `UnknownTypeError` and its messages: why a topic's type cannot be recorded in this
  interpreter, naming the wheel to install (`wheel_name`);
- `RecordingStats`: per topic what was recorded (type, messages, bytes, first and last receive
  time) and each type that could not be, for the recorder's stats file;
- `probe_timeout_message`: what a probe that heard nothing says, for each reason it can have.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from nodes.recording.errors import RecordingError

#: The ROS distribution whose PyPI wheels (`ros-<distro>-<package>`) the testbed installs.
DISTRO = "jazzy"

RELIABLE, BEST_EFFORT = "reliable", "best_effort"
TRANSIENT_LOCAL, VOLATILE = "transient_local", "volatile"

# A ROS package or type name: what rosidl accepts (letters, digits, underscores).
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class TopicSelectionError(RecordingError, ValueError):
    """A `--topic`, `--regex` or node name that cannot be used (the message says which)."""


class UnknownTypeError(RecordingError):
    """A topic's type cannot be recorded in this interpreter; the message says what to install."""


# ---- which topics -----------------------------------------------------------------------------


def normalize_topic(name: str) -> str:
    """A topic name as the ROS graph spells it: fully qualified (`chatter` -> `/chatter`)."""
    text = name.strip()
    if not text or text == "/" or any(c.isspace() for c in text):
        raise TopicSelectionError(f"not a ROS topic name: {name!r}")
    return text if text.startswith("/") else f"/{text}"


def check_node_name(name: str) -> str:
    """`name` if ROS accepts it as a node name, else a clear error (rclpy's is a traceback)."""
    if not _NODE_NAME.match(name):
        raise TopicSelectionError(
            f"node name {name!r}: use letters, digits and underscores, not starting with a digit"
        )
    return name


@dataclass(frozen=True)
class TopicSelector:
    """The topics to record: each equal to one of `topics` or in which one of `patterns` is
    found (`re.search` on the full name, so `^/chat` anchors and `camera` matches anywhere)."""

    topics: frozenset[str] = frozenset()
    patterns: tuple[re.Pattern[str], ...] = ()

    @classmethod
    def parse(cls, topics: Iterable[str] = (), regexes: Iterable[str] = ()) -> TopicSelector:
        compiled = []
        for text in regexes:
            try:
                compiled.append(re.compile(text))
            except re.error as err:
                raise TopicSelectionError(
                    f"--regex {text!r} is not a regular expression: {err}"
                ) from None
        selector = cls(frozenset(normalize_topic(t) for t in topics), tuple(compiled))
        if selector.empty:
            raise TopicSelectionError("give at least one --topic or --regex to record")
        return selector

    @property
    def empty(self) -> bool:
        return not self.topics and not self.patterns

    def matches(self, topic: str) -> bool:
        return topic in self.topics or any(p.search(topic) for p in self.patterns)

    def to_dict(self) -> dict[str, list[str]]:
        return {"topics": sorted(self.topics), "regex": [p.pattern for p in self.patterns]}


# ---- with what QoS ----------------------------------------------------------------------------


@dataclass(frozen=True)
class QosChoice:
    """A reliability (`reliable`/`best_effort`) and durability (`transient_local`/`volatile`),
    of a publisher as discovered or of the subscription chosen for it."""

    reliability: str = BEST_EFFORT
    durability: str = VOLATILE

    def receives_from(self, publisher: QosChoice) -> bool:
        """DDS's request-offered rule: a subscription asking for reliable (transient local)
        delivery matches only publishers offering it; best effort (volatile) matches all."""
        if self.reliability == RELIABLE and publisher.reliability != RELIABLE:
            return False
        return not (self.durability == TRANSIENT_LOCAL and publisher.durability != TRANSIENT_LOCAL)

    def to_dict(self) -> dict[str, str]:
        return {"reliability": self.reliability, "durability": self.durability}


def adapted_qos(publishers: Sequence[QosChoice]) -> QosChoice:
    """The strongest QoS that still receives from every publisher (what rosbag2 does):
    reliable if all of them are (no message lost to the recorder where the app would lose
    none), transient local if all of them are (a late recorder still gets a latched message);
    else best effort / volatile, which matches any publisher. No publishers: best effort."""
    if not publishers:
        return QosChoice()
    reliable = all(p.reliability == RELIABLE for p in publishers)
    durable = all(p.durability == TRANSIENT_LOCAL for p in publishers)
    return QosChoice(
        RELIABLE if reliable else BEST_EFFORT, TRANSIENT_LOCAL if durable else VOLATILE
    )


# ---- which types ------------------------------------------------------------------------------


def wheel_name(package: str, distro: str = DISTRO) -> str:
    """The PyPI wheel (and Debian package) of a ROS package: `std_msgs` -> `ros-jazzy-std-msgs`."""
    return f"ros-{distro}-{package.replace('_', '-').lower()}"


def split_type_name(type_name: str) -> tuple[str, str]:
    """(package, Type) of a message type `pkg/msg/Type`; anything else (a service's or an
    action's hidden topics, `pkg/action/T_FeedbackMessage`) is an `UnknownTypeError`."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg" and _NAME.match(parts[0]) and _NAME.match(parts[2]):
        return parts[0], parts[2]
    if len(parts) == 3 and parts[1] in ("srv", "action"):
        raise UnknownTypeError(
            f"{type_name}: only message types (pkg/msg/Type) are recorded, not the hidden "
            f"topics of {'a service' if parts[1] == 'srv' else 'an action'}"
        )
    raise UnknownTypeError(f"{type_name}: not a ROS message type name (pkg/msg/Type)")


def package_missing(type_name: str, detail: str = "") -> str:
    """The message for a type whose package's Python module does not import here."""
    package, _ = split_type_name(type_name)
    why = f" ({detail})" if detail else ""
    return (
        f"{type_name}: package {package} is not installed in this interpreter{why}; "
        f"pip install {wheel_name(package)}"
    )


def type_missing(type_name: str) -> str:
    """The message for a type that its (installed) package does not have."""
    package, name = split_type_name(type_name)
    return (
        f"{type_name}: package {package} is installed but has no message {name} (another "
        f"version of it?); pip install --upgrade {wheel_name(package)}"
    )


def definition_missing(type_name: str, detail: str) -> str:
    """The message for a type whose Python module imports but whose `.msg` file (the schema a
    recording carries, so that readers without ROS decode it) is not found."""
    package, name = split_type_name(type_name)
    return (
        f"{type_name}: package {package} imports but its definition {package}/msg/{name}.msg "
        f"is not installed, and a recording needs it as the schema ({detail}); "
        f"pip install --force-reinstall {wheel_name(package)}"
    )


# ---- what was recorded ------------------------------------------------------------------------


@dataclass
class TopicRecord:
    """One recorded topic's figures; times are receive times in ns since the epoch."""

    type: str
    qos: QosChoice
    messages: int = 0
    bytes: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    subscriptions: int = 1  # > 1: resubscribed with a weaker QoS for a new publisher

    def to_dict(self) -> dict[str, Any]:
        return {
            "type": self.type,
            "messages": self.messages,
            "bytes": self.bytes,
            "first_time": None if self.first_ns is None else self.first_ns / 1e9,
            "last_time": None if self.last_ns is None else self.last_ns / 1e9,
            "qos": self.qos.to_dict(),
            "subscriptions": self.subscriptions,
        }


@dataclass
class RecordingStats:
    """What a recorder took and what it could not: updated from its executor thread only."""

    topics: dict[str, TopicRecord] = field(default_factory=dict)
    #: (topic, type) -> why that type cannot be recorded on that topic.
    unknown: dict[tuple[str, str], str] = field(default_factory=dict)

    def subscribed(self, topic: str, type_name: str, qos: QosChoice) -> None:
        """A subscription to `topic` was created (again, with `qos`, if it existed)."""
        record = self.topics.get(topic)
        if record is None:
            self.topics[topic] = TopicRecord(type_name, qos)
        else:
            record.qos = qos
            record.subscriptions += 1

    def message(self, topic: str, size: int, t_ns: int) -> None:
        record = self.topics[topic]
        record.messages += 1
        record.bytes += size
        if record.first_ns is None:
            record.first_ns = t_ns
        record.last_ns = t_ns

    def failed(self, topic: str, type_name: str, error: str) -> bool:
        """Remember why `type_name` on `topic` cannot be recorded; True the first time (the
        caller logs it once instead of on every poll of the graph)."""
        if (topic, type_name) in self.unknown:
            return False
        self.unknown[(topic, type_name)] = error
        return True

    def known_failure(self, topic: str, type_name: str) -> bool:
        return (topic, type_name) in self.unknown

    def to_dict(self) -> dict[str, Any]:
        return {
            "messages": sum(r.messages for r in self.topics.values()),
            "bytes": sum(r.bytes for r in self.topics.values()),
            "topics": {t: r.to_dict() for t, r in sorted(self.topics.items())},
            "type_errors": len(self.unknown),
            "unknown_types": [
                {"topic": t, "type": k, "error": e} for (t, k), e in sorted(self.unknown.items())
            ],
        }


# ---- what a probe says ------------------------------------------------------------------------


def probe_timeout_message(
    topic: str, timeout_s: float, seen: bool, publishers: int, types: Sequence[str] = ()
) -> str:
    """Why a probe of `topic` heard nothing within `timeout_s`: the topic never appeared in the
    graph, appeared without a publisher (only subscribers), or had publishers that sent
    nothing (or nothing this probe could match)."""
    head = f"no message on {topic} within {timeout_s:g} s: "
    if not seen:
        return head + (
            "the topic never appeared in the ROS graph (is the app running and publishing it, "
            "in this ROS domain, with discovery peers that reach it?)"
        )
    if publishers == 0:
        return head + (
            "the topic is in the ROS graph but never had a publisher (only subscribers: is "
            "the publishing app running?)"
        )
    kinds = f" of {', '.join(types)}" if types else ""
    return head + (
        f"the topic was seen with {publishers} publisher(s){kinds}, but none published a "
        "message in that time"
    )
