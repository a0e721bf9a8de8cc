"""The relay process of a userspace link: two TUN ends, two pipelines, one event loop.

    python -m netem.relay --netns-a NS_A --dev-a tunA --netns-b NS_B --dev-b tunB \\
        --control /run/x.sock [--addr-a 10.0.0.1/30 --addr-b 10.0.0.2/30 --mtu 1500]
        [--uplink '{"delay_s": 0.01}' --downlink '{...}' --seed 1 --die-with-parent]
        [--no-offload]

Packets read from end A (namespace A) go through the *uplink* pipeline and are written to end
B; packets from B go through the *downlink* pipeline to A. One thread, one selector: it sleeps
until a packet arrives, a control request comes, or the next packet is due.

Offloads (the default): both TUN ends announce TSO/USO (`netem.tun`), so TCP hands the relay
super-packets of up to 64 kB (`netem.gso.Frame`) and one read, one pipeline pass and one write
move ~44 wire packets. The pipeline splits them only where an effect is per wire packet (its
`Segment` stage), and what such a stage hands out at one instant (a slot's transport block, a
burst) goes back into super-packets before it is written (`netem.gso.rejoin`). `--no-offload`
reads and writes one MTU-sized packet at a time (the data plane before offloads; kept to
measure against and for kernels without TUN offloads).

Timing: `select` oversleeps, by ~0.1 ms plus, on some VMs, a share of the sleep itself (a
guest timer running a few per cent slow: 0.5 ms late after 10 ms). The relay sets its timer
slack to 1 ns and learns both parts, so it sleeps short of a packet's departure (at most
0.3 ms plus the learnt share), sleeps again for what is left, and polls the last stretch;
deadlines farther away are pure sleeps, so an idle link costs no CPU. Polling has a CPU budget
(10% of a core); past it, on a busy link, a packet due within the oversleep leaves that much
early instead, so the error stays centred on zero.

Control: a unix stream socket; one JSON object per line in, one JSON reply per line out:
    {"op": "ping"}                                             -> {"ok": true, "pid": ...}
    {"op": "set", "direction": "uplink"|"downlink"|"both", "profile": {field: value, ...}}
    {"op": "outage", "seconds": 2.0, "direction": "both"}
    {"op": "interrupt", "seconds": 0.04, "mode": "hold"|"drop", "direction": "both"}
    {"op": "trace", "direction": "uplink", "path": "x.csv"|null, "format": "csv", "loop": true}
    {"op": "counters"}                          -> {"ok": true, "uplink": {...}, "downlink": ...}
    {"op": "attach", "link": "av2-gnb1", "netns_a": ..., "dev_a": ..., "netns_b": ...,
     "dev_b": ..., "mtu": 1500, "uplink": {...}, "downlink": {...}, "seed": "...",
     "cell": "gnb1"}                                            -> {"ok": true}
    {"op": "detach", "link": "av2-gnb1"}
Errors come back as {"ok": false, "error": "..."}; the relay keeps running. `set` changes only
the fields given (the others keep their value) and applies in place: queued packets stay.
`outage` drops what enters the link; `interrupt` is a handover's gap (`netem.stages.HandoverGap`,
seconds in 0..10, mode default hold): what would leave the link during it waits for its end
("hold", a lossless handover) or is lost ("drop"); the loop wakes at the end to deliver it.
`counters` reports a direction's gaps under its "handover" (absent until one was started;
`since` and `until` of the last on the relay's clock, CLOCK_MONOTONIC).

RRC states (a profile's `rrc`, `netem.rrc`) are the UE's, not a direction's: each link has one
state machine that both its directions' packets drive (`netem.stages.share_rrc`), so its two
profiles always carry the same `rrc`: a `set` that names `rrc` changes it in both directions
(its reply shows both profiles), and a link whose two profiles differ in it is refused. The
UE is connected when its link comes up (it has just attached) and when a `set` switches RRC
states on; its timers run from then.
`counters` reports the link's RRC state and promotions under "rrc" (null without RRC states),
and each direction's share of them (promotions its packets started, packets held) under its
own "rrc".

One relay can carry several links (`attach`; each its own two TUN ends and pipelines; every
request but `ping` and `attach` names its `link`, the first one by default). Links that name
the same `cell` (`--cell` for the first) share that cell's NR slots (`netem.cell.Cell`), per
direction: the air links of one gNB.

On start it prints one line `{"event": "ready", ...}` to stdout once both TUNs are up and the
control socket listens. SIGTERM or SIGINT -> clean exit (the TUN devices vanish with it).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import signal
import socket
import sys
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from netem.cell import SCHEDULERS, Cell, CellError
from netem.errors import NetemError, ProfileError
from netem.gso import VNET_LEN, Frame, ip_packets, rejoin
from netem.pcap import PcapngWriter
from netem.proc import PR_SET_TIMERSLACK, die_with_parent, prctl, renice
from netem.profile import PROFILE_FIELDS, LinkProfile, check_link, check_profile
from netem.stages import Pipeline, RrcLink, RrcStage, Slots, check_gap, share_rrc
from netem.traces import TRACE_FORMATS, load_trace
from netem.tun import MAX_MTU, TunConfig, TunError, open_tun_in

#: Packets read from one TUN per wake-up before the loop looks at deadlines again.
READ_BATCH = 64
#: How overdue a departure may get before a batch of reads stops for it.
READ_SLACK_S = 0.0001
#: Bounds of the early wake-up, which tracks the measured timer oversleep. The loop polls
#: (spins) only for a packet due within the early wake-up, so never for more than the maximum.
EARLY_MIN_S, EARLY_MAX_S = 0.00002, 0.0003
#: A sleep longer than this also teaches the timer's stretch (oversleep per second asked),
#: which is capped: a host 25% slow is broken, not slow.
STRETCH_FROM_S, STRETCH_MAX = 0.001, 0.25
#: Share of a core the loop may spend polling, and the most it may save up (seconds).
SPIN_SHARE, SPIN_BURST_S = 0.1, 0.005
DIRECTIONS = ("uplink", "downlink")


class ControlError(NetemError, ValueError):
    """A control request that cannot be carried out; its message goes back to the client."""


class WakeTimer:
    """Decides how long the loop may sleep, learning how late this host's timers fire.

    A packet due within the expected oversleep is waited for by polling (spinning), which
    makes it leave on time. Spinning is paid from a budget that refills at `spin_share` of
    a core: on a busy link, where deadlines come every few tens of µs, polling would take a
    whole core, so once the budget is spent such packets leave up to `early_s` ahead of time
    instead (`ahead_s`), which centres the timing error on zero at no CPU cost.
    """

    def __init__(self, spin_share: float = SPIN_SHARE) -> None:
        self.early_s = 0.0001  # the VM's median oversleep, refined as we go
        self.stretch = 0.0  # extra oversleep per second of sleep asked (a slow guest timer)
        self.spin_share = spin_share
        self.spin_budget_s = SPIN_BURST_S
        self.ahead_s = 0.0  # how early a packet may leave after this plan
        self.sleeps = 0
        self.spins = 0
        self.early_releases = 0
        self._last: float | None = None
        self._spinning = False

    def timeout(self, soft: float | None, hard: float | None, now: float) -> float | None:
        """Seconds to block in select (None: until an event; 0: poll).

        `hard` is when a packet leaves the link (it must be on time); `soft` is a hand-off
        between stages (exact whenever it is handled), so it never causes a spin.
        """
        if self._last is not None:
            elapsed = now - self._last
            if self._spinning:
                self.spin_budget_s -= elapsed
            self.spin_budget_s = min(SPIN_BURST_S, self.spin_budget_s + elapsed * self.spin_share)
        self._last = now
        self._spinning = False
        self.ahead_s = 0.0
        timeout: float | None = None
        if soft is not None:
            timeout = max(0.0, soft - now)
        if hard is not None:
            wait = hard - now
            if wait <= 0:
                return 0.0
            if wait <= self.early_s:
                # Due within the oversleep (always < 0.3 ms): a sleep would be late.
                if self.spin_budget_s > 0:
                    self._spinning = True
                    self.spins += 1
                else:
                    self.ahead_s = self.early_s
                    self.early_releases += 1
                return 0.0
            # Twice the learnt stretch: its wake-ups scatter about as much again, and one
            # short sleep more (for what is left) costs far less than a late packet.
            sleep = (wait - self.early_s) / (1.0 + 2.0 * self.stretch)
            if timeout is None or sleep < timeout:
                timeout = sleep
        return timeout

    def observe(self, asked: float, slept: float) -> None:
        """Feed back a sleep that ended by timeout, to track the oversleep (EWMAs).

        A short sleep's oversleep is the fixed part (`early_s`); what a long one oversleeps
        beyond that, per second asked, is the stretch.
        """
        if asked <= 0:
            return
        self.sleeps += 1
        over = max(slept - asked, 0.0)
        if asked > STRETCH_FROM_S:
            share = min(max(over - self.early_s, 0.0) / asked, STRETCH_MAX)
            self.stretch = 0.9 * self.stretch + 0.1 * share
            over -= self.stretch * asked
        over = min(max(over, 0.0), 0.002)
        early = 0.95 * self.early_s + 0.05 * over
        self.early_s = min(max(early, EARLY_MIN_S), EARLY_MAX_S)


class Port:
    """One link of a relay: its two TUN fds and its uplink (A -> B) and downlink pipelines."""

    def __init__(
        self, name: str, fd_a: int, fd_b: int, uplink: Pipeline, downlink: Pipeline
    ) -> None:
        self.name = name
        self.fd_a, self.fd_b = fd_a, fd_b
        self.pipelines = {"uplink": uplink, "downlink": downlink}
        self.cell: str | None = None
        self.capture: Capture | None = None


def _dropped(pipeline: Pipeline) -> int:
    """Packets the direction's stages dropped so far, every reason together."""
    return sum(pipeline.snapshot()["total"]["dropped_packets"].values())


class Capture:
    """A pcapng file of what one link delivers, per direction (one interface each), written as
    packets leave the link: after every impairment, so dropped packets are not in it; their
    number goes into the file's interface statistics when it is closed. With TUN offloads a
    super-packet is written as the wire packets it stands for (`Relay._deliver`)."""

    def __init__(self, path: str, port: Port, label: str | None = None) -> None:
        self.path = path
        self.writer = PcapngWriter(path)
        name = label or port.name
        self.interfaces = {d: self.writer.interface(f"{name} {d}") for d in DIRECTIONS}
        self._dropped0 = {d: _dropped(port.pipelines[d]) for d in DIRECTIONS}
        self.packets = {d: 0 for d in DIRECTIONS}

    def write(self, direction: str, packet: bytes) -> None:
        self.writer.packet(
            self.interfaces[direction], packet, time.time_ns(),
            direction="outbound" if direction == "uplink" else "inbound",
        )  # fmt: skip
        self.packets[direction] += 1

    def close(self, port: Port) -> dict[str, Any]:
        """Finish the file: interface statistics, final name; returns what it holds."""
        now = time.time_ns()
        dropped = {}
        for d in DIRECTIONS:
            dropped[d] = _dropped(port.pipelines[d]) - self._dropped0[d]
            self.writer.statistics(self.interfaces[d], now, self.packets[d], dropped[d])
        self.writer.close()
        return {"path": self.path, "packets": dict(self.packets), "dropped": dropped}


class Relay:
    """Moves packets between TUN fds through an uplink and a downlink `Pipeline` per link."""

    def __init__(
        self,
        fd_a: int,
        fd_b: int,
        uplink: Pipeline,
        downlink: Pipeline,
        control_path: str | None = None,
        mtu: int = 1500,
        clock: Callable[[], float] = time.monotonic,
        offload: bool = False,
        name: str = "link",
        cell: str | None = None,
        scheduler: str = "rr",
    ) -> None:
        self.ports: dict[str, Port] = {}
        self.first = name
        self.mtu = mtu
        self.cells: dict[tuple[str, str], Cell] = {}  # (cell, direction) -> its shared slots
        self.scheduler = scheduler
        self.clock = clock
        self.offload = offload
        # A super-packet is at most an IP packet's 64 kB behind its virtio-net header.
        self.read_size = VNET_LEN + MAX_MTU if offload else max(mtu, 1500) + 64
        self.timer = WakeTimer()
        self.lateness: deque[float] = deque(maxlen=20000)  # recent exit lateness samples
        self.stats = {
            "wakeups": 0,
            "read_batches": 0,
            "write_errors": 0,
            "control_requests": 0,
            "reads": 0,  # frames read: with offloads one may be many wire packets
            "writes": 0,
            "write_calls": 0,
        }
        self._running = True
        self._hard: float | None = None  # the next departure, as the loop last planned
        # select(2) directly: µs timeouts (epoll's are whole ms) and the least work per call
        # on a handful of fds. fd -> (kind, argument).
        self._handlers: dict[int, tuple[str, Any]] = {}
        self._conns: dict[socket.socket, bytearray] = {}
        self._listener: socket.socket | None = None
        self._control_path = control_path
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._handlers[self._wake_r.fileno()] = ("wake", None)
        self._add_port(Port(name, fd_a, fd_b, uplink, downlink), cell)
        self._fds = list(self._handlers)  # what select() watches, rebuilt when it changes
        if control_path is not None:
            self._listen(control_path)

    @property
    def pipelines(self) -> dict[str, Pipeline]:
        """The first link's pipelines (a relay of one link has no other)."""
        return self.ports[self.first].pipelines

    def _add_port(self, port: Port, cell: str | None) -> None:
        if port.name in self.ports:
            raise ControlError(f"this relay already carries a link named {port.name!r}")
        try:
            # One RRC state machine for the UE of this link, whichever direction its packets go.
            rrc = share_rrc(port.pipelines["uplink"], port.pipelines["downlink"])
        except ProfileError as exc:
            raise ControlError(f"link {port.name}: {exc}") from None
        if rrc is not None:
            rrc.start(self.clock())  # the link is up: its UE has just attached, connected
        if cell is not None:
            for d, pipeline in port.pipelines.items():
                stage = pipeline.stage("slots")
                assert isinstance(stage, Slots)
                shared = self.cells.setdefault((cell, d), Cell(self.scheduler))
                try:
                    shared.join(stage)
                except CellError as exc:
                    for joined in self.cells.values():
                        joined.leave(pipeline.stage("slots"))  # type: ignore[arg-type]
                    raise ControlError(f"link {port.name} cannot join cell {cell}: {exc}") from None
            port.cell = cell
        self.ports[port.name] = port
        self._handlers[port.fd_a] = ("tun", port.pipelines["uplink"])
        self._handlers[port.fd_b] = ("tun", port.pipelines["downlink"])
        self._fds = list(self._handlers)
        self._outputs = self._output_list()

    def _remove_port(self, name: str) -> Port:
        port = self._port({"link": name})
        if name == self.first:
            raise ControlError(f"{name} is this relay's first link: stop the relay instead")
        if port.capture is not None:
            with contextlib.suppress(OSError):
                port.capture.close(port)
            port.capture = None
        for d, pipeline in port.pipelines.items():
            if port.cell is not None:
                self.cells[port.cell, d].leave(pipeline.stage("slots"))  # type: ignore[arg-type]
        for fd in (port.fd_a, port.fd_b):
            self._handlers.pop(fd, None)
        self._fds = list(self._handlers)
        del self.ports[name]
        self._outputs = self._output_list()
        return port

    def _output_list(self) -> list[tuple[Pipeline, int, Port, str]]:
        """Each pipeline with the TUN fd it writes to, its port and direction."""
        out = []
        for port in self.ports.values():
            out += [
                (port.pipelines["uplink"], port.fd_b, port, "uplink"),
                (port.pipelines["downlink"], port.fd_a, port, "downlink"),
            ]
        return out

    @staticmethod
    def _rrc(port: Port) -> RrcLink | None:
        """The RRC state of the link's UE (None: pipelines made without an RRC stage)."""
        stage = next((s for s in port.pipelines["uplink"].stages if isinstance(s, RrcStage)), None)
        return None if stage is None else stage.link

    def _port(self, request: dict[str, Any]) -> Port:
        name = request.get("link", self.first)
        if name not in self.ports:
            raise ControlError(
                f"no link {name!r} in this relay (it carries {', '.join(self.ports)})"
            )
        return self.ports[name]

    def _attach(self, request: dict[str, Any]) -> None:
        name = request.get("link")
        if not isinstance(name, str) or not name:
            raise ControlError("attach needs `link`: the link's name")
        if name in self.ports:
            raise ControlError(f"this relay already carries a link named {name!r}")
        try:
            mtu = int(request.get("mtu", self.mtu))
            ends = [
                (
                    str(request[f"netns_{e}"]),
                    TunConfig(
                        str(request[f"dev_{e}"]),
                        mtu,
                        request.get(f"addr_{e}"),
                        offload=self.offload,
                    ),
                )
                for e in "ab"
            ]
            profiles = {d: LinkProfile.from_dict(dict(request.get(d) or {})) for d in DIRECTIONS}
        except KeyError as exc:
            raise ControlError(f"attach needs {exc.args[0]!r}") from None
        for profile in profiles.values():
            check_profile(profile)
        check_link(profiles["uplink"], profiles["downlink"])  # before any TUN end is opened
        seed = str(request.get("seed", name))
        uplink = Pipeline.from_profile(profiles["uplink"], f"{seed}:uplink", "uplink")
        downlink = Pipeline.from_profile(profiles["downlink"], f"{seed}:downlink", "downlink")
        fds: list[int] = []
        try:
            for netns, config in ends:
                fds.append(open_tun_in(netns, config))
            cell = request.get("cell")
            self._add_port(Port(name, fds[0], fds[1], uplink, downlink), cell)
        except (TunError, OSError) as exc:
            for fd in fds:
                os.close(fd)
            raise ControlError(f"attach {name}: {exc}") from None
        except ControlError:
            for fd in fds:
                os.close(fd)
            raise

    # -- control ----------------------------------------------------------------------------

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
        if op == "ping":
            return {"pid": os.getpid()}
        if op == "counters":
            return self.counters(self._port(request))
        if op == "attach":
            self._attach(request)
            return {}
        if op == "detach":
            port = self._remove_port(str(request.get("link")))
            for fd in (port.fd_a, port.fd_b):
                os.close(fd)
            return {}
        port = self._port(request)
        if op == "set":
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
        if op == "outage":
            seconds = request.get("seconds")
            if not isinstance(seconds, int | float) or not seconds >= 0:
                raise ControlError(f"outage needs `seconds` >= 0, got {seconds!r}")
            now = self.clock()
            for d in self._directions(request, default="both"):
                port.pipelines[d].outage(now, float(seconds))
            return {}
        if op == "interrupt":
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
        if op == "capture":
            return self._capture(port, request)
        if op == "trace":
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
        raise ControlError(
            f"unknown op {op!r}; allowed: ping, set, outage, interrupt, trace, capture, counters, "
            "attach, detach"
        )

    def _capture(self, port: Port, request: dict[str, Any]) -> dict[str, Any]:
        """Start (`path`; `label` names its interfaces, default the link's name here) or stop
        (`stop`: true) the link's capture; a stop returns what the file holds."""
        if request.get("stop"):
            if port.capture is None:
                return {}
            capture, port.capture = port.capture, None
            return capture.close(port)
        path = request.get("path")
        if not isinstance(path, str) or not path.endswith(".pcapng"):
            raise ControlError(f"capture needs `path`, a .pcapng file name, got {path!r}")
        if port.capture is not None:
            raise ControlError(f"link {port.name} is already captured to {port.capture.path}")
        try:
            label = request.get("label")
            port.capture = Capture(path, port, label if isinstance(label, str) else None)
        except OSError as exc:
            raise ControlError(f"cannot write capture {path}: {exc.strerror}") from None
        return {"path": path}

    def counters(self, port: Port | None = None) -> dict[str, Any]:
        port = port if port is not None else self.ports[self.first]
        times = os.times()
        late = sorted(self.lateness)
        lateness = {
            f"p{q}": late[min(len(late) - 1, int(q / 100 * len(late)))] if late else None
            for q in (50, 90, 99)
        }
        rrc = self._rrc(port)
        return {
            "uplink": port.pipelines["uplink"].snapshot(),
            "downlink": port.pipelines["downlink"].snapshot(),
            "rrc": None if rrc is None else rrc.counters(self.clock()),
            "cell": port.cell,
            "scheduler": self.scheduler if port.cell is not None else None,
            "relay": {
                **self.stats,
                "offload": self.offload,
                "cpu_s": times.user + times.system,
                "early_wake_s": self.timer.early_s,
                "timer_stretch": self.timer.stretch,
                "timed_sleeps": self.timer.sleeps,
                "spins": self.timer.spins,
                "early_releases": self.timer.early_releases,
                "exit_lateness_s": lateness,
            },
        }

    # -- packets ----------------------------------------------------------------------------

    def _read(self, fd: int, pipeline: Pipeline) -> None:
        self.stats["read_batches"] += 1
        clock, push, size = self.clock, pipeline.push, self.read_size
        offload = self.offload
        stats = self.stats
        # A batch stops once a departure is READ_SLACK_S overdue: a busy link's reads must not
        # make another packet leave late (the rest is read right after the departure), and a
        # little slack keeps a saturated link's batches long.
        due = self._hard + READ_SLACK_S if self._hard is not None else float("inf")
        for _ in range(READ_BATCH):
            try:
                packet = os.read(fd, size)
            except BlockingIOError:
                return
            stats["reads"] += 1
            now = clock()
            push(Frame(packet) if offload else packet, now)
            if now >= due:
                return

    def _deliver(self, now: float) -> None:
        offload = self.offload
        for pipeline, fd, port, direction in self._outputs:
            handoff, exit_ = pipeline.deadlines()
            if (exit_ is None or exit_ > now) and (handoff is None or handoff > now):
                continue  # nothing of this direction is due: leave its stages alone
            if exit_ is not None and exit_ <= now:
                # How late the first packet of this batch leaves (after the clock read).
                self.lateness.append(self.clock() - exit_)
            out = pipeline.pop_ready(now)
            self.stats["writes"] += len(out)
            capture = port.capture
            if offload and len(out) > 1:
                writes = rejoin(out)
            else:
                writes = [(p.data if offload else p, 1) for p in out]  # type: ignore[attr-defined]
            self.stats["write_calls"] += len(writes)
            end = 0  # `out[end - count : end]` is what this write carries
            for data, count in writes:
                end += count
                try:
                    os.write(fd, data)
                except OSError:
                    # The far end is down or its queue is full: the packets are lost, as on
                    # a wire; count them so a report can tell.
                    self.stats["write_errors"] += count
                    continue
                if capture is not None:
                    # The packets as a wire carries them, as they left the stages (not as
                    # rejoined): a super-packet (a TCP or a UDP-GSO run, such as a GTP-U
                    # end's G-PDUs) segment by segment, so every frame in the file is one
                    # packet, one G-PDU on N3.
                    for packet in out[end - count : end]:
                        wire = packet.data if offload else packet  # type: ignore[attr-defined]
                        for one in ip_packets(wire) if offload else (wire,):
                            capture.write(direction, one)

    def _deadlines(self) -> tuple[float | None, float | None]:
        """(earliest hand-off or exit, earliest exit) over both directions."""
        soft: float | None = None
        hard: float | None = None
        for pipeline, _fd, _port, _direction in self._outputs:
            due, exit_ = pipeline.deadlines()
            if due is not None and (soft is None or due < soft):
                soft = due
            if exit_ is not None and (hard is None or exit_ < hard):
                hard = exit_
        return soft, hard

    def stop(self) -> None:
        """Ask the loop to end (safe from a signal handler)."""
        self._running = False
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")

    def run(self) -> None:
        """Relay until `stop()`."""
        clock, timer, handlers = self.clock, self.timer, self._handlers
        stats = self.stats
        while self._running:
            now = clock()
            soft, self._hard = self._deadlines()
            timeout = timer.timeout(soft, self._hard, now)
            try:
                ready = select.select(self._fds, [], [], timeout)[0]
            except InterruptedError:  # pragma: no cover - PEP 475 retries; kept for safety
                ready = []
            stats["wakeups"] += 1
            if not ready and timeout:
                timer.observe(timeout, clock() - now)
            for fd in ready:
                kind, arg = handlers.get(fd, ("gone", None))
                if kind == "tun":
                    self._read(fd, arg)
                elif kind == "listen":
                    self._accept()
                elif kind == "conn":
                    self._serve(arg)
                elif kind == "wake":
                    with contextlib.suppress(OSError):
                        self._wake_r.recv(4096)
            # A packet written into a TUN end is processed by the kernel in that very write,
            # and what it answers (a TCP sender's next data after an ACK) is readable at once:
            # reading it now saves a select() wake-up per answer.
            self._deliver(clock() + timer.ahead_s)

    def close(self) -> None:
        """Finish the captures, close the control socket and the TUN ends of attached links
        (the first link's fds are its opener's)."""
        for port in self.ports.values():
            if port.capture is not None:
                with contextlib.suppress(OSError):
                    port.capture.close(port)
                port.capture = None
        for name in [n for n in self.ports if n != self.first]:
            port = self._remove_port(name)
            for fd in (port.fd_a, port.fd_b):
                with contextlib.suppress(OSError):
                    os.close(fd)
        for conn in list(self._conns):
            self._drop_conn(conn)
        if self._listener is not None:
            self._handlers.pop(self._listener.fileno(), None)
            self._listener.close()
            self._listener = None
            if self._control_path:
                with contextlib.suppress(OSError):
                    os.unlink(self._control_path)
        self._wake_r.close()
        self._wake_w.close()


def _profile_arg(text: str) -> LinkProfile:
    try:
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("expected a JSON object of LinkProfile fields")
        unknown = sorted(set(data) - set(PROFILE_FIELDS))
        if unknown:
            raise ValueError(f"unknown field(s) {unknown}; allowed: {', '.join(PROFILE_FIELDS)}")
        profile = LinkProfile.from_dict(data)
        check_profile(profile)
    except (ValueError, TypeError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return profile


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m netem.relay", description=__doc__.split("\n")[0])
    p.add_argument("--netns-a", required=True, help="namespace of end A (name or path)")
    p.add_argument("--netns-b", required=True, help="namespace of end B (name or path)")
    p.add_argument("--dev-a", required=True, help="TUN device name of end A")
    p.add_argument("--dev-b", required=True, help="TUN device name of end B")
    p.add_argument("--addr-a", help="address of end A, e.g. 10.0.0.1/30")
    p.add_argument("--addr-b", help="address of end B, e.g. 10.0.0.2/30")
    p.add_argument("--mtu", type=int, default=1500, help=f"MTU of both ends (68..{MAX_MTU})")
    p.add_argument("--name", default="link", help="the first link's name (in control requests)")
    p.add_argument(
        "--cell", help="share NR slots with the links attached to the same cell (a gNB's name)"
    )
    p.add_argument(
        "--scheduler", choices=SCHEDULERS, default="rr", help="how a cell shares its slots"
    )
    p.add_argument("--control", help="path of the control unix socket")
    p.add_argument("--uplink", type=_profile_arg, default=LinkProfile(), help="A->B profile JSON")
    p.add_argument("--downlink", type=_profile_arg, default=LinkProfile(), help="B->A profile")
    p.add_argument("--seed", default="0", help="seed of loss and jitter draws")
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="scheduling priority change (negative = sooner; an emulated link should not wait"
        " behind the workload it carries)",
    )
    p.add_argument(
        "--die-with-parent", action="store_true", help="exit when the starting process dies"
    )
    p.add_argument(
        "--no-offload",
        dest="offload",
        action="store_false",
        help="one MTU-sized packet per read and write (no TSO/USO super-packets)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    prctl(PR_SET_TIMERSLACK, 1)  # 1 ns slack: timers fire as asked
    renice("relay", args.nice)
    if args.die_with_parent and not die_with_parent():
        return 1
    try:
        end_a = TunConfig(args.dev_a, args.mtu, args.addr_a, offload=args.offload)
        end_b = TunConfig(args.dev_b, args.mtu, args.addr_b, offload=args.offload)
    except ValueError as exc:
        print(f"relay: error: {exc}", file=sys.stderr)
        return 2
    fds: list[int] = []
    relay: Relay | None = None
    try:
        fds.append(open_tun_in(args.netns_a, end_a))
        fds.append(open_tun_in(args.netns_b, end_b))
        uplink = Pipeline.from_profile(args.uplink, f"{args.seed}:uplink", "uplink")
        downlink = Pipeline.from_profile(args.downlink, f"{args.seed}:downlink", "downlink")
        relay = Relay(
            fds[0],
            fds[1],
            uplink,
            downlink,
            args.control,
            mtu=args.mtu,
            offload=args.offload,
            name=args.name,
            cell=args.cell,
            scheduler=args.scheduler,
        )
    except (TunError, OSError, ValueError) as exc:
        print(f"relay: error: {exc}", file=sys.stderr)
        for fd in fds:
            os.close(fd)
        return 1
    signal.signal(signal.SIGTERM, lambda *_: relay.stop())
    signal.signal(signal.SIGINT, lambda *_: relay.stop())
    ready = {"event": "ready", "pid": os.getpid(), "dev_a": args.dev_a, "dev_b": args.dev_b}
    print(json.dumps(ready), flush=True)
    try:
        relay.run()
    finally:
        relay.close()
        for fd in fds:
            os.close(fd)
    return 0


if __name__ == "__main__":
    sys.exit(main())
