"""The relay's control protocol: a unix stream socket, one JSON object per line in, one JSON
reply per line out.

Errors come back as {"ok": false, "error": "..."}; the relay keeps running. `set` changes only
the fields given (the others keep their value) and applies in place: queued packets stay.
`outage` drops what enters the link; `interrupt` is a handover's gap
(`netem.nr.handover_gap.HandoverGap`, seconds in 0..10, mode default hold): what would leave
the link during it waits for its end ("hold", a lossless handover) or is lost ("drop"); the
loop wakes at the end to deliver it. `counters` reports a direction's gaps under its
"handover" (absent until one was started; `since` and `until` of the last on the relay's
clock, CLOCK_MONOTONIC).

RRC states (a profile's `rrc`, `netem.nr.rrc`) are the UE's, not a direction's: each link has
one state machine that both its directions' packets drive (`netem.nr.rrc_stage.share_rrc`), so
its two profiles always carry the same `rrc`: a `set` that names `rrc` changes it in both
directions (its reply shows both profiles), and a link whose two profiles differ in it is
refused. The UE is connected when its link comes up (it has just attached) and when a `set`
switches RRC states on; its timers run from then. `counters` reports the link's RRC state and
promotions under "rrc" (null without RRC states), and each direction's share of them
(promotions its packets started, packets held) under its own "rrc".

Every request but `ping` and `attach` names its `link`, the first one by default. The
requests, one per entry of `OPS` (whose keys are also what the error for an unknown op allows),
with the reply's fields where it has more than `ok`:

"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from netem.directions import DIRECTIONS
from netem.errors import NetemError, ProfileError
from netem.nr.handover_gap import check_gap
from netem.profile import PROFILE_FIELDS, LinkProfile, check_profile
from netem.relay.capture import Capture
from netem.traces import TRACE_FORMATS, load_trace


class ControlError(NetemError, ValueError):
    """A control request that cannot be carried out; its message goes back to the client."""


class Control:
    """The control side of a relay (`netem.relay.process.Relay`, which is one): its socket,
    the requests and their replies. It drives the relay's links (`ports`, `first`), its clock
    and its select set (`_handlers`, `_fds`), and asks the relay to attach, detach and count."""

    ports: dict[str, Any]
    first: str
    clock: Callable[[], float]
    stats: dict[str, int]
    _handlers: dict[int, tuple[str, Any]]
    _fds: list[int]
    _conns: dict[socket.socket, bytearray]
    _listener: socket.socket | None

    def counters(self, port: Any = None) -> dict[str, Any]:
        raise NotImplementedError

    def _attach(self, request: dict[str, Any]) -> None:
        raise NotImplementedError

    def _remove_port(self, name: str) -> Any:
        raise NotImplementedError

    def _rrc(self, port: Any) -> Any:
        raise NotImplementedError

    def _listen(self, path: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.bind(path)
        os.chmod(path, 0o600)
        sock.listen(8)
        sock.setblocking(False)
        self._listener = sock
        self._handlers[sock.fileno()] = ("listen", None)
        self._fds = list(self._handlers)

    def _accept(self) -> None:
        assert self._listener is not None
        try:
            conn, _ = self._listener.accept()
        except BlockingIOError:
            return
        conn.settimeout(1.0)  # replies are small; never let a stuck client stall the link
        self._conns[conn] = bytearray()
        self._handlers[conn.fileno()] = ("conn", conn)
        self._fds = list(self._handlers)

    def _drop_conn(self, conn: socket.socket) -> None:
        self._handlers.pop(conn.fileno(), None)
        self._fds = list(self._handlers)
        self._conns.pop(conn, None)
        conn.close()

    def _serve(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(65536)
        except OSError:
            data = b""
        if not data:
            self._drop_conn(conn)
            return
        buf = self._conns[conn]
        buf += data
        if len(buf) > 1 << 20:
            self._drop_conn(conn)
            return
        while b"\n" in buf:
            line, _, rest = bytes(buf).partition(b"\n")
            buf[:] = rest
            if not line.strip():
                continue
            reply = self.handle_line(line)
            try:
                conn.sendall((json.dumps(reply) + "\n").encode())
            except OSError:
                self._drop_conn(conn)
                return

    def handle_line(self, line: bytes) -> dict[str, Any]:
        """Answer one control request (a JSON line); never raises."""
        self.stats["control_requests"] += 1
        try:
            request = json.loads(line)
            if not isinstance(request, dict):
                raise ControlError("a request must be a JSON object")
            return {"ok": True, **self.handle(request)}
        except json.JSONDecodeError as exc:
            return {"ok": False, "error": f"request is not JSON: {exc}"}
        except (ControlError, ValueError, TypeError) as exc:
            return {"ok": False, "error": str(exc)}

    def _port(self, request: dict[str, Any]) -> Any:
        name = request.get("link", self.first)
        if name not in self.ports:
            raise ControlError(
                f"no link {name!r} in this relay (it carries {', '.join(self.ports)})"
            )
        return self.ports[name]

    def _directions(self, request: dict[str, Any], default: str | None = None) -> list[str]:
        direction = request.get("direction", default)
        if direction == "both":
            return list(DIRECTIONS)
        if direction not in DIRECTIONS:
            raise ControlError(
                f"direction must be uplink, downlink or both, got {direction!r}"
                if direction is not None
                else "direction is missing (uplink, downlink or both)"
            )
        return [direction]

    def handle(self, request: dict[str, Any]) -> dict[str, Any]:
        """Carry out one control request and return the reply's fields."""
        op = request.get("op")
        entry = OPS.get(op) if isinstance(op, str) else None
        # A request that names no known op still has its link looked up first, as one that
        # does: an unknown link is the error it gets.
        port = self._port(request) if entry is None or entry.per_link else None
        if entry is None:
            raise ControlError(f"unknown op {op!r}; allowed: {', '.join(OPS)}")
        return entry.run(self, request, port)

    def _ping(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        return {"pid": os.getpid()}

    def _counters(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        return self.counters(port)

    def _attach_op(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        self._attach(request)
        return {}

    def _detach(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        port = self._remove_port(str(request.get("link")))
        for fd in (port.fd_a, port.fd_b):
            os.close(fd)
        return {}

    def _set(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        changes = request.get("profile")
        if not isinstance(changes, dict):
            raise ControlError("set needs `profile`: an object of LinkProfile fields")
        unknown = sorted(set(changes) - set(PROFILE_FIELDS))
        if unknown:
            raise ControlError(
                f"unknown profile field(s) {unknown}; allowed: {', '.join(PROFILE_FIELDS)}"
            )
        targets = self._directions(request)
        new = {}
        for d in DIRECTIONS:
            current = port.pipelines[d].profile.to_dict()
            if d in targets:
                merged = {**current, **changes}
            elif "rrc" in changes:
                # The RRC state is the UE's (TS 38.331 §4.2.1): one machine, one setting.
                merged = {**current, "rrc": changes["rrc"]}
            else:
                continue
            profile = LinkProfile.from_dict(merged)
            check_profile(profile)
            new[d] = profile
        for d, profile in new.items():  # all validated first: both or neither change
            port.pipelines[d].apply(profile)
        rrc = self._rrc(port)
        if rrc is not None:
            rrc.start(self.clock())  # RRC states switched on: connected from now
        return {"profiles": {d: p.to_dict() for d, p in new.items()}}

    def _outage(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        seconds = request.get("seconds")
        if not isinstance(seconds, int | float) or not seconds >= 0:
            raise ControlError(f"outage needs `seconds` >= 0, got {seconds!r}")
        now = self.clock()
        for d in self._directions(request, default="both"):
            port.pipelines[d].outage(now, float(seconds))
        return {}

    def _interrupt(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        seconds, mode = request.get("seconds"), request.get("mode", "hold")
        try:
            check_gap(seconds, mode)
        except ProfileError as exc:
            raise ControlError(f"interrupt: {exc}") from None
        directions = self._directions(request, default="both")
        now = self.clock()  # one instant for both directions: one handover
        for d in directions:
            port.pipelines[d].interrupt(now, float(seconds), mode)
        return {}

    def _trace(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        targets = self._directions(request)
        path = request.get("path")
        fmt = request.get("format")
        if fmt is not None and fmt not in TRACE_FORMATS:
            raise ControlError(f"trace format must be mahimahi or csv, got {fmt!r}")
        trace = None if path is None else load_trace(str(path), fmt)
        now = self.clock()
        for d in targets:
            port.pipelines[d].play_trace(trace, now, loop=bool(request.get("loop", False)))
        return {"mean_rate_bps": None if trace is None else trace.mean_rate_bps()}

    def _capture(self, request: dict[str, Any], port: Any) -> dict[str, Any]:
        """Start (`path`; `label` names its interfaces, default the link's name here) or stop
        (`stop`: true) the link's capture; a stop returns what the file holds."""
        if request.get("stop"):
            if port.capture is None:
                return {}
            capture, port.capture = port.capture, None
            return capture.close()
        path = request.get("path")
        if not isinstance(path, str) or not path.endswith(".pcapng"):
            raise ControlError(f"capture needs `path`, a .pcapng file name, got {path!r}")
        if port.capture is not None:
            raise ControlError(f"link {port.name} is already captured to {port.capture.path}")
        try:
            label = request.get("label")
            name = label if isinstance(label, str) and label else port.name
            port.capture = Capture(path, name, port.pipelines)
        except OSError as exc:
            raise ControlError(f"cannot write capture {path}: {exc.strerror}") from None
        return {"path": path}


@dataclass(frozen=True)
class Op:
    """One request of the protocol."""

    #: Carries it out: (the relay, the request, its link or None) -> the reply's fields.
    run: Callable[[Control, dict[str, Any], Any], dict[str, Any]]
    #: It names a link (`link`, the first by default), which is looked up before it runs.
    per_link: bool
    #: The request, and the reply where it has more than `ok`, as the docstring shows it.
    usage: str


#: Every request, in the order the module docstring and the error for an unknown op list them.
OPS: dict[str, Op] = {
    "ping": Op(Control._ping, False, '{"op": "ping"}  -> {"ok": true, "pid": ...}'),
    "set": Op(
        Control._set,
        True,
        '{"op": "set", "direction": "uplink"|"downlink"|"both", "profile": {field: value, ...}}',
    ),
    "outage": Op(Control._outage, True, '{"op": "outage", "seconds": 2.0, "direction": "both"}'),
    "interrupt": Op(
        Control._interrupt,
        True,
        '{"op": "interrupt", "seconds": 0.04, "mode": "hold"|"drop", "direction": "both"}',
    ),
    "trace": Op(
        Control._trace,
        True,
        '{"op": "trace", "direction": "uplink", "path": "x.csv"|null, "format": "csv", '
        '"loop": true}\n        -> {"ok": true, "mean_rate_bps": ...}',
    ),
    "capture": Op(
        Control._capture,
        True,
        '{"op": "capture", "path": "x.pcapng", "label": "av1"}  -> {"ok": true, "path": ...}\n'
        '    {"op": "capture", "stop": true}  -> {"ok": true, "path": ..., "packets": ..., '
        '"dropped": ...}',
    ),
    "counters": Op(
        Control._counters, True, '{"op": "counters"}  -> {"ok": true, "uplink": {...}, ...}'
    ),
    "attach": Op(
        Control._attach_op,
        False,
        '{"op": "attach", "link": "av2-gnb1", "netns_a": ..., "dev_a": ..., "netns_b": ...,\n'
        '     "dev_b": ..., "mtu": 1500, "uplink": {...}, "downlink": {...}, "seed": "...",\n'
        '     "cell": "gnb1"}',
    ),
    "detach": Op(Control._detach, False, '{"op": "detach", "link": "av2-gnb1"}'),
}

__doc__ = (__doc__ or "") + "".join(f"    {op.usage}\n" for op in OPS.values())
