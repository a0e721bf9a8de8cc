"""Cross-traffic of a run (`traffic:`): each flow's two generator ends in their namespaces.

Nouns:
- `FlowEnd`: one `nodes.traffic.gen` process (a receiver or a sender) of one flow: started
  through `Node.popen` (so the run's state lists it and teardown stops it), with its log
  `logs/traffic.<flow>.<role>.log`, its stats `nodes/traffic.<flow>.<role>.json` and its
  samples `traffic/<flow>.<role>.jsonl`.
- `CrossTraffic`: all flows of a run. Receivers start before the timeline and the run waits for
  their ready lines; a sender is started a second before its `start` with `--start-at` that
  instant (CLOCK_MONOTONIC, shared by all namespaces), so it begins on time whatever Python's
  start-up costs, and `--duration` ends it at its `stop`. A generator end that exits non-zero
  fails the run with its log. `stop()` ends the senders first (their last datagrams tell the
  receiver how many were sent), then the receivers, and returns what run.json and the report
  show per flow: offered rate, goodput, loss, one-way delay, RTT, and the sender's own
  lateness (a starved generator is visible, not silent).

`samples()` gives every sample line of every end, for `/traffic/<flow>` in run.mcap.

The generator is checked against iperf3. `python -m pytest -s tests/test_byo_root.py` on a
2-core VM: a 30 Mbit/s UDP flow through a 20 Mbit/s air uplink lost 31.7% over 10 s (35% in
steady state: what arrived late in the burst still drains from the link's queue after it), bulk
TCP then carried 18.88 Mbit/s of the 19.29 Mbit/s of payload the link holds, and an rclpy
subscriber the test wrote got av1's fused poses at 20.0/s both as an app and through `testbed
exec`. With cross-traffic on, the report's "EdgeLoc under load" table sets each vehicle's request
latency and error while a flow ran against the rest of the run.
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import signal
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from ipaddress import IPv4Address
from pathlib import Path
from typing import Any

from testbed.errors import TestbedError
from testbed.scenario.model import Traffic
from testbed.topology import Net

Progress = Callable[[str], None]

#: How long a receiver may take to bind and say it is ready.
READY_TIMEOUT_S = 20.0
#: A sender is started this long before its start time (its imports take ~0.3 s here).
LEAD_S = 1.0
#: Between stopping the senders and the receivers: the senders' last datagrams land.
DRAIN_S = 0.4
STOP_GRACE_S = 3.0
TAIL_LINES = 10


def address_of(net: Net, node: str, seen_from: str) -> IPv4Address:
    """The address `seen_from`'s packets reach `node` at: a vehicle's UE (or air) address; for
    any other node, its address on the last link of the shortest path from `seen_from`."""
    if net.scenario.topology.role_of(node) == "vehicle":
        return net.vehicle_address(node)
    neighbours: dict[str, list[str]] = {}
    for link in net.links.values():
        neighbours.setdefault(link.lower.name, []).append(link.upper.name)
        neighbours.setdefault(link.upper.name, []).append(link.lower.name)
    previous: dict[str, str] = {seen_from: seen_from}
    queue = deque([seen_from])
    while queue:
        here = queue.popleft()
        for there in neighbours.get(here, []):
            if there not in previous:
                previous[there] = here
                queue.append(there)
    if node not in previous:
        raise TestbedError(f"no path from {seen_from} to {node} in the topology")
    return net.nodes[node].address_towards(previous[node])


@dataclass
class FlowEnd:
    """One generator process of a flow (see the module doc)."""

    flow: Traffic
    role: str  # "recv" or "send"
    log: Path
    stats: Path
    samples: Path
    proc: subprocess.Popen[Any] | None = None
    stopped: bool = False

    @property
    def name(self) -> str:
        return f"{self.flow.name}.{self.role}"

    def tail(self) -> str:
        try:
            lines = self.log.read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return "\n".join(lines[-TAIL_LINES:]) or "(empty log)"

    def read_stats(self) -> dict[str, Any]:
        try:
            data = json.loads(self.stats.read_text())
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}


class CrossTraffic:
    """The flows of one run (see the module doc)."""

    def __init__(self, net: Net, folder: Path, progress: Progress) -> None:
        self.net, self.folder, self.progress = net, Path(folder), progress
        self.flows = list(net.scenario.traffic)
        self.ends: list[FlowEnd] = []
        self.t0: float | None = None  # CLOCK_MONOTONIC at the timeline's 0 s
        self.stopping = False
        for f in self.flows:
            for role in ("recv", "send"):
                base = f"traffic.{f.name}.{role}"
                self.ends.append(
                    FlowEnd(
                        f,
                        role,
                        self.folder / "logs" / f"{base}.log",
                        self.folder / "nodes" / f"{base}.json",
                        self.folder / "traffic" / f"{f.name}.{role}.jsonl",
                    )
                )

    def __bool__(self) -> bool:
        return bool(self.flows)

    def _end(self, flow: Traffic, role: str) -> FlowEnd:
        return next(e for e in self.ends if e.flow is flow and e.role == role)

    # ---- start -------------------------------------------------------------------------

    def _argv(self, end: FlowEnd, start_at: float | None = None) -> list[str]:
        f = end.flow
        kind = "tcp" if f.kind == "tcp" else "udp"
        argv = [sys.executable, "-m", "nodes.traffic.gen", end.role]
        common = ["--port", str(f.port), "--stats", str(end.stats), "--samples", str(end.samples)]
        common.append("--die-with-parent")
        if end.role == "recv":
            return [*argv, "--kind", kind, *common]
        to = address_of(self.net, f.dst, f.src)
        argv += ["--kind", f.kind, "--to", str(to), *common, "--size", str(f.size)]
        if f.rate_bps is not None:
            argv += ["--rate", f"{f.rate_bps:.0f}"]
        if f.kind == "onoff":
            argv += ["--on", f"{f.on_s:g}", "--off", f"{f.off_s:g}"]
        if f.stop_s is not None:
            argv += ["--duration", f"{f.stop_s - f.start_s:.3f}"]
        if start_at is not None:
            argv += ["--start-at", f"{start_at:.6f}"]
        return argv

    def _popen(self, end: FlowEnd, argv: list[str], ready_pipe: bool) -> None:
        for path in (end.log, end.stats, end.samples):
            path.parent.mkdir(parents=True, exist_ok=True)
        node = end.flow.dst if end.role == "recv" else end.flow.src
        with open(end.log, "w") as log:
            end.proc = self.net[node].popen(
                argv,
                what=f"{node}: traffic {end.name}",
                stdout=subprocess.PIPE if ready_pipe else log,
                stderr=log,
                stdin=subprocess.DEVNULL,
                text=True,
            )

    def start_receivers(self) -> None:
        """Start every flow's receiver and wait until each is bound and listening."""
        for f in self.flows:
            end = self._end(f, "recv")
            self._popen(end, self._argv(end), ready_pipe=True)
        for f in self.flows:
            self._wait_ready(self._end(f, "recv"))
        shown = ", ".join(f"{f.name} ({f.kind} {f.src}->{f.dst}:{f.port})" for f in self.flows)
        self.progress(f"  traffic receivers ready: {shown}")

    def _wait_ready(self, end: FlowEnd) -> None:
        assert end.proc is not None and end.proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(end.proc.stdout, selectors.EVENT_READ)
            line = end.proc.stdout.readline() if sel.select(READY_TIMEOUT_S) else ""
        if not line.startswith('{"event": "ready"'):
            raise TestbedError(
                f"run {self.net.run_id} failed: traffic {end.name} did not start "
                f"({line.strip() or f'no ready line within {READY_TIMEOUT_S:g} s'}); "
                f"last lines of {end.log}:\n{end.tail()}"
            )

    def timeline_started(self) -> None:
        """The timeline's 0 s is now: sender start times count from here."""
        self.t0 = time.monotonic()

    # ---- watch -------------------------------------------------------------------------

    def tick(self, elapsed: float) -> None:
        """Start the senders due within `LEAD_S`; fail if a generator end died."""
        if self.stopping:
            return
        if self.t0 is None:
            self.timeline_started()
            assert self.t0 is not None
            self.t0 -= elapsed
        for f in self.flows:
            end = self._end(f, "send")
            if end.proc is None and f.start_s - LEAD_S <= elapsed:
                start_at = self.t0 + f.start_s
                self._popen(end, self._argv(end, max(start_at, time.monotonic())), False)
                self.progress(
                    f"  traffic {f.name}: {f.kind} {f.src} -> {f.dst} from t={f.start_s:g} s"
                    + (f" to {f.stop_s:g} s" if f.stop_s is not None else "")
                )
        for end in self.ends:
            if end.proc is None or end.stopped:
                continue
            code = end.proc.poll()
            if code is None:
                continue
            if code == 0 and end.role == "send" and end.flow.stop_s is not None:
                end.stopped = True  # its --duration is over
                continue
            raise TestbedError(
                f"run {self.net.run_id} failed: traffic {end.name} exited with {code}; "
                f"last lines of {end.log}:\n{end.tail()}"
            )

    # ---- stop --------------------------------------------------------------------------

    def _signal(self, ends: list[FlowEnd]) -> None:
        for end in ends:
            end.stopped = True
            if end.proc is not None and end.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(end.proc.pid, signal.SIGTERM)

    def _wait(self, ends: list[FlowEnd]) -> None:
        for end in ends:
            if end.proc is None:
                continue
            try:
                end.proc.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                self.progress(f"  warning: traffic {end.name} did not stop; killed")
                end.proc.kill()
                end.proc.wait(timeout=5)
            if end.proc.stdout is not None:
                end.proc.stdout.close()

    def stop(self) -> dict[str, Any]:
        """Senders, then receivers (see the module doc); returns `summary()`."""
        self.stopping = True
        senders = [e for e in self.ends if e.role == "send"]
        receivers = [e for e in self.ends if e.role == "recv"]
        self._signal(senders)
        self._wait(senders)
        if any(e.proc is not None for e in senders):
            time.sleep(DRAIN_S)
        self._signal(receivers)
        self._wait(receivers)
        return self.summary()

    def summary(self) -> dict[str, Any]:
        """Per flow: the spec, both ends' figures and exit codes."""
        out: dict[str, Any] = {}
        for f in self.flows:
            send, recv = self._end(f, "send"), self._end(f, "recv")
            s, r = send.read_stats(), recv.read_stats()
            out[f.name] = {
                "kind": f.kind,
                "from": f.src,
                "to": f.dst,
                "port": f.port,
                "rate_bps": f.rate_bps,
                "size": f.size,
                "start_s": f.start_s,
                "stop_s": f.stop_s,
                "sent_bps": s.get("sent_bps"),
                "goodput_bps": r.get("goodput_bps"),
                "loss": r.get("loss"),
                "delay_p50_ms": r.get("delay_p50_ms"),
                "delay_p95_ms": r.get("delay_p95_ms"),
                "rtt_p50_ms": s.get("rtt_p50_ms"),
                "rtt_p95_ms": s.get("rtt_p95_ms"),
                "late_packets": s.get("late_packets"),
                "packets_sent": s.get("packets_sent"),
                "packets_received": r.get("packets_received"),
                "active_s": r.get("active_s"),
                "exit_codes": {
                    e.role: (e.proc.returncode if e.proc is not None else None)
                    for e in (send, recv)
                },
                "errors": {**(s.get("errors") or {}), **(r.get("errors") or {})},
                "stats": {
                    "send": str(send.stats.relative_to(self.folder)),
                    "recv": str(recv.stats.relative_to(self.folder)),
                },
            }
        return out

    def samples(self) -> Iterator[tuple[Traffic, dict[str, Any]]]:
        """Every sample line of every end, in file order."""
        for end in self.ends:
            try:
                lines = end.samples.read_text().splitlines()
            except OSError:
                continue
            for line in lines:
                with contextlib.suppress(ValueError):
                    sample = json.loads(line)
                    if isinstance(sample, dict):
                        yield end.flow, sample
