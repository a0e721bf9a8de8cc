"""The relay's event loop (`Relay`): its links' TUN ends, their pipelines, one selector.

Packets read from end A (namespace A) go through the *uplink* pipeline and are written to end
B; packets from B go through the *downlink* pipeline to A. One thread, one selector: it sleeps
until a packet arrives, a control request comes (`netem.relay.control`), or the next packet is
due (`netem.relay.timer`).

Offloads (the default): both TUN ends announce TSO/USO (`netem.tun`), so TCP hands the relay
super-packets of up to 64 kB (`netem.gso.Frame`) and one read, one pipeline pass and one write
move ~44 wire packets. The pipeline splits them only where an effect is per wire packet (its
`Segment` stage), and what such a stage hands out at one instant (a slot's transport block, a
burst) goes back into super-packets before it is written (`netem.gso.rejoin`). Without
offloads the relay reads and writes one MTU-sized packet at a time (the data plane before
offloads; kept to measure against and for kernels without TUN offloads).

One relay can carry several links (`attach`; each its own two TUN ends and pipelines). Links
that name the same `cell` share that cell's NR slots (`netem.nr.cell.Cell`), per direction:
the air links of one gNB.

Where a super-packet is split into its wire packets (software GSO, full checksums, which the
receiving kernel verifies): a loss gate splits one only if it loses some of its packets; a
bandwidth trace gives every packet its own delivery opportunity; a rate that would keep one on
the wire more than 2 ms splits it; a full queue admits the segments that fit. Counters, queue
limits and the rate charge what the packets weigh on a wire (headers repeated per segment).
What is joined again (software GRO) is a TCP flow's segments that run in sequence, so the far
end takes a slot's transport block in one write.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from netem.directions import DIRECTIONS
from netem.errors import ProfileError
from netem.gso import VNET_LEN, Frame, ip_packets, rejoin
from netem.nr.cell import Cell, CellError
from netem.nr.rrc_stage import RrcLink, RrcStage, share_rrc
from netem.nr.ue import Slots
from netem.profile import LinkProfile, check_link, check_profile
from netem.relay.capture import Capture
from netem.relay.control import Control, ControlError
from netem.relay.direction import build_pipeline
from netem.relay.timer import WakeTimer
from netem.stages import Pipeline
from netem.tun import MAX_MTU, TunConfig, TunError, open_tun_in

#: Packets read from one TUN per wake-up before the loop looks at deadlines again.
READ_BATCH = 64
#: How overdue a departure may get before a batch of reads stops for it.
READ_SLACK_S = 0.0001


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


class Relay(Control):
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
                port.capture.close()
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
        uplink = build_pipeline(profiles["uplink"], f"{seed}:uplink", "uplink")
        downlink = build_pipeline(profiles["downlink"], f"{seed}:downlink", "downlink")
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
                    port.capture.close()
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
