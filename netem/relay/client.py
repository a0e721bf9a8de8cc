"""`UserspaceLink`: one emulated link between two namespaces, carried by a relay process.

    with UserspaceLink("ns-a", "ns-b", dev_a="ul0", dev_b="ul0",
                       addr_a="10.9.0.1/30", addr_b="10.9.0.2/30",
                       uplink=LinkProfile(delay_s=0.005), downlink=LinkProfile()) as link:
        link.set("uplink", LinkProfile(delay_s=0.020))      # live, in place
        link.counters()["uplink"]["total"]["packets_out"]

The link owns the relay (`python -m netem.relay`): it starts it, waits for its ready line,
talks to it over the control socket and stops it on `close()`. A link made with `host=`
another link has no process of its own: it is attached to the host's relay (two more TUN
ends, its own pipelines) and detached on `close()`; links of one `cell` share its NR slots:

    with UserspaceLink(..., cell="gnb1") as first:
        with UserspaceLink(..., name="av2-gnb1", cell="gnb1", host=first) as second:
            ... `alive()` is false as soon as
the relay has exited; `watch()` runs a thread that calls back (within `interval_s`) when it
dies, and `check()` raises `RelayError` with the relay's last words.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import netem
from netem.directions import Directions
from netem.errors import NetemError
from netem.profile import LinkProfile, check_link, check_profile


class RelayError(NetemError, RuntimeError):
    """The relay could not start, refused a request, or died; the message says which."""


@dataclass(frozen=True)
class RelayEnd:
    """One end of the link: the namespace, the TUN device name in it, and its address."""

    netns: str
    dev: str
    address: str | None = None


class UserspaceLink:
    """A link between namespace A (uplink sender) and B; a context manager.

    `uplink` shapes A->B, `downlink` B->A. `seed` makes loss and jitter reproducible.
    `die_with_parent` ends the relay if this process dies (leave it False for links that must
    outlive the process that made them, e.g. `testbed up`; then `pid` is what to stop).
    `offload` lets TCP hand the relay 64 kB super-packets (`netem.gso`); False moves one
    MTU-sized packet at a time, the data plane before offloads.
    `nice` raises the relay's priority (-10 by default: on a 2-core host busy with the
    workload, a relay that waits for a CPU adds milliseconds of delay the profile never asked
    for; it takes no more CPU for it). Use 0 when not running as root.
    `name` is the link's name in its relay; `cell` the NR cell whose slots it shares with the
    relay's other links of that cell (`netem.nr.cell`, `scheduler` "rr" or "pf"); `host` a
    started link whose relay carries this one too.
    """

    def __init__(
        self,
        netns_a: str,
        netns_b: str,
        *,
        dev_a: str,
        dev_b: str,
        addr_a: str | None = None,
        addr_b: str | None = None,
        mtu: int = 1500,
        uplink: LinkProfile | None = None,
        downlink: LinkProfile | None = None,
        seed: int | str = 0,
        control_path: str | os.PathLike[str] | None = None,
        log_dir: str | os.PathLike[str] | None = None,
        die_with_parent: bool = True,
        nice: int = -10,
        python: str = sys.executable,
        offload: bool = True,
        name: str = "link",
        cell: str | None = None,
        scheduler: str = "rr",
        host: UserspaceLink | None = None,
    ) -> None:
        self.a = RelayEnd(netns_a, dev_a, addr_a)
        self.b = RelayEnd(netns_b, dev_b, addr_b)
        self.mtu = mtu
        self.profiles = {
            "uplink": uplink if uplink is not None else LinkProfile(),
            "downlink": downlink if downlink is not None else LinkProfile(),
        }
        for profile in self.profiles.values():
            check_profile(profile)
        # One RRC state machine serves both directions: refused here rather than by the relay.
        check_link(self.profiles["uplink"], self.profiles["downlink"])
        self.seed = seed
        self.die_with_parent = die_with_parent
        self.nice = nice
        self.python = python
        self.offload = offload
        self.name = name
        self.cell = cell
        self.scheduler = scheduler
        self.host = host
        self._attached = False
        # Without a log_dir the relay's log (and control socket) go to a temp folder of ours,
        # removed on close; with one, the caller owns the folder and its lifetime.
        self._log_dir = None if log_dir is None else str(log_dir)
        self._tmpdir: str | None = None
        self._control_path = None if control_path is None else str(control_path)
        self._proc: subprocess.Popen[bytes] | None = None
        self._log_path: str | None = None
        self._closing = False
        self._lock = threading.Lock()
        self._watcher: threading.Thread | None = None

    # -- life cycle -------------------------------------------------------------------------

    @property
    def pid(self) -> int | None:
        if self.host is not None:
            return self.host.pid if self._attached else None
        return None if self._proc is None else self._proc.pid

    @property
    def control_path(self) -> str | None:
        return self.host.control_path if self.host is not None else self._control_path

    def command(self) -> list[str]:
        """The relay's command line."""
        cmd = [
            self.python,
            "-m",
            "netem.relay",
            "--netns-a",
            self.a.netns,
            "--dev-a",
            self.a.dev,
            "--netns-b",
            self.b.netns,
            "--dev-b",
            self.b.dev,
            "--mtu",
            str(self.mtu),
            "--uplink",
            json.dumps(self.profiles["uplink"].to_dict()),
            "--downlink",
            json.dumps(self.profiles["downlink"].to_dict()),
            "--seed",
            str(self.seed),
        ]
        if self._control_path:
            cmd += ["--control", self._control_path]
        if self.a.address:
            cmd += ["--addr-a", self.a.address]
        if self.b.address:
            cmd += ["--addr-b", self.b.address]
        if self.nice:
            cmd += ["--nice", str(self.nice)]
        if self.die_with_parent:
            cmd.append("--die-with-parent")
        if not self.offload:
            cmd.append("--no-offload")
        if self.name != "link":
            cmd += ["--name", self.name]
        if self.cell is not None:
            cmd += ["--cell", self.cell, "--scheduler", self.scheduler]
        return cmd

    def _attach(self) -> UserspaceLink:
        assert self.host is not None
        if self._attached:
            raise RelayError(f"link {self.name} is already attached")
        self.host.request(
            {
                "op": "attach",
                "link": self.name,
                "netns_a": self.a.netns,
                "dev_a": self.a.dev,
                "netns_b": self.b.netns,
                "dev_b": self.b.dev,
                "addr_a": self.a.address,
                "addr_b": self.b.address,
                "mtu": self.mtu,
                "uplink": self.profiles["uplink"].to_dict(),
                "downlink": self.profiles["downlink"].to_dict(),
                "seed": str(self.seed),
                "cell": self.cell,
            },
            timeout_s=10.0,
        )
        self._attached = True
        return self

    def start(self, timeout_s: float = 10.0) -> UserspaceLink:
        """Start the relay and wait until both TUN ends are up; raise `RelayError` if not.

        A link with a `host` is attached to the host's relay instead."""
        if self.host is not None:
            return self._attach()
        return self.launch().wait_ready(timeout_s)

    def launch(self) -> UserspaceLink:
        """Start the relay process without waiting for it (`wait_ready` then does): several
        relays launched first and waited for together come up in the time of the slowest,
        not of all of them in turn. Not for a link with a `host` (`start` attaches it)."""
        if self.host is not None:
            raise RelayError(f"{self.describe()} joins its host's relay: start() attaches it")
        if self._proc is not None:
            raise RelayError("this link's relay is already started")
        if self._log_dir is None:
            self._tmpdir = tempfile.mkdtemp(prefix="netem-relay-")
        folder = self._log_dir or self._tmpdir
        assert folder is not None
        if self._control_path is None:
            self._control_path = os.path.join(folder, "control.sock")
        self._log_path = os.path.join(folder, "relay.log")
        env = dict(os.environ)
        # The relay imports this very package, installed or not.
        root = str(Path(netem.__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
        with open(self._log_path, "wb") as log:
            self._proc = subprocess.Popen(
                self.command(),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=log,
                env=env,
                start_new_session=True,  # a ^C in the terminal reaches us, and we stop it
            )
        return self

    def wait_ready(self, timeout_s: float = 10.0) -> UserspaceLink:
        """Wait until the launched relay's TUN ends are up; on failure (`RelayError`) the
        relay is closed."""
        try:
            if self._proc is None:
                raise RelayError(f"the relay for {self.describe()} was not launched")
            self._wait_ready(timeout_s)
        except BaseException:
            self.close()
            raise
        return self

    def _wait_ready(self, timeout_s: float) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        with selectors.DefaultSelector() as sel:
            sel.register(self._proc.stdout, selectors.EVENT_READ)
            while time.monotonic() < deadline:
                if not sel.select(max(0.0, deadline - time.monotonic())):
                    break
                line = self._proc.stdout.readline()
                if not line:
                    self._proc.wait(timeout=2)
                    raise RelayError(
                        f"relay for {self.describe()} exited with code {self._proc.returncode}"
                        f" before it was ready: {self.log_tail() or 'no message'}"
                    )
                with contextlib.suppress(ValueError):
                    if json.loads(line).get("event") == "ready":
                        return
        raise RelayError(f"relay for {self.describe()} not ready after {timeout_s:.0f} s")

    def describe(self) -> str:
        return f"{self.a.netns}/{self.a.dev} <-> {self.b.netns}/{self.b.dev}"

    def log_tail(self, limit: int = 2000) -> str:
        """The end of what the relay wrote to stderr."""
        if not self._log_path:
            return ""
        try:
            return Path(self._log_path).read_text(errors="replace")[-limit:].strip()
        except OSError:
            return ""

    @property
    def closing(self) -> bool:
        """Being closed (or its host is): a relay that goes now has not died."""
        return self._closing or (self.host is not None and self.host.closing)

    def alive(self) -> bool:
        """True while the relay process runs."""
        if self.host is not None:
            return self._attached and self.host.alive()
        return self._proc is not None and self._proc.poll() is None

    def check(self) -> None:
        """Raise `RelayError` if the relay is not running (it died or was never started)."""
        if self.host is not None:
            if not self._attached:
                raise RelayError(f"link {self.name} was never attached to its host's relay")
            self.host.check()
            return
        if self._proc is None:
            raise RelayError(f"relay for {self.describe()} was never started")
        code = self._proc.poll()
        if code is not None:
            raise RelayError(
                f"relay for {self.describe()} died (exit code {code}); the link is down. "
                f"{self.log_tail()}".strip()
            )

    def watch(
        self, on_death: Callable[[RelayError], None] | None = None, interval_s: float = 0.2
    ) -> threading.Thread:
        """Watch the relay from a daemon thread; call `on_death(error)` once if it dies.

        Without `on_death` the error is printed to stderr. A `close()` is not a death.
        """

        def run() -> None:
            while not self.closing:
                try:
                    self.check()
                except RelayError as exc:
                    if self.closing:
                        return
                    if on_death is None:
                        print(f"error: {exc}", file=sys.stderr, flush=True)
                    else:
                        on_death(exc)
                    return
                time.sleep(interval_s)

        self._watcher = threading.Thread(target=run, name=f"relay-watch-{self.pid}", daemon=True)
        self._watcher.start()
        return self._watcher

    def close(self, timeout_s: float = 3.0) -> None:
        """Stop the relay (SIGTERM, then SIGKILL) and remove its files; safe to repeat.

        An attached link is detached from its host's relay, which keeps running."""
        self._closing = True
        if self.host is not None:
            if self._attached and self.host.alive():
                with contextlib.suppress(RelayError):
                    self.host.request({"op": "detach", "link": self.name})
            self._attached = False
            return
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=timeout_s)
            if proc.stdout is not None:
                proc.stdout.close()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> UserspaceLink:
        if self._proc is None and not self._attached:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- control ----------------------------------------------------------------------------

    def request(self, message: dict[str, Any], timeout_s: float = 2.0) -> dict[str, Any]:
        """Send one control request and return the reply; raise `RelayError` on failure."""
        if self.host is not None:
            self.check()
            return self.host.request({**message, "link": self.name}, timeout_s)
        self.check()
        assert self._control_path is not None
        with self._lock:
            try:
                with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
                    sock.settimeout(timeout_s)
                    sock.connect(self._control_path)
                    sock.sendall((json.dumps(message) + "\n").encode())
                    data = b""
                    while not data.endswith(b"\n"):
                        chunk = sock.recv(65536)
                        if not chunk:
                            break
                        data += chunk
            except OSError as exc:
                raise RelayError(f"relay for {self.describe()} does not answer: {exc}") from None
        try:
            reply = json.loads(data)
        except json.JSONDecodeError:
            raise RelayError(f"relay for {self.describe()} sent a bad reply {data!r}") from None
        if not reply.get("ok"):
            raise RelayError(f"relay refused {message.get('op')!r}: {reply.get('error')}")
        return reply

    def set(self, direction: Directions, profile: LinkProfile | dict[str, Any]) -> None:
        """Change one direction (or both) in place: a `LinkProfile` replaces it whole, a
        dict changes only the fields it names. `rrc` is the link's, not a direction's: the
        relay changes it in both directions, and `profiles` shows both."""
        if isinstance(profile, LinkProfile):
            check_profile(profile)
            changes = profile.to_dict()
        else:
            # A model given as an object (a Radio, a Gilbert-Elliott chain) goes as its fields.
            changes = {
                k: v.to_dict()
                if hasattr(v, "to_dict")
                else dataclasses.asdict(v)
                if dataclasses.is_dataclass(v)
                else v  # type: ignore[arg-type]
                for k, v in profile.items()
            }
        reply = self.request({"op": "set", "direction": direction, "profile": changes})
        for d, data in reply.get("profiles", {}).items():
            self.profiles[d] = LinkProfile.from_dict(data)

    def outage(self, seconds: float, direction: Directions = "both") -> None:
        """Drop every packet on the link for `seconds` from now."""
        self.request({"op": "outage", "seconds": seconds, "direction": direction})

    def interrupt(self, seconds: float, mode: str = "hold", direction: Directions = "both") -> None:
        """A handover's interruption of `seconds` from now: packets that would leave the link
        meanwhile wait for its end and then leave in order (`mode` "hold", a lossless
        handover) or are lost ("drop"). Unlike `outage`, it cuts what is in flight too."""
        self.request({"op": "interrupt", "seconds": seconds, "mode": mode, "direction": direction})

    def play_trace(
        self,
        direction: Directions,
        path: str | os.PathLike[str] | None,
        format: str | None = None,
        loop: bool = False,
    ) -> None:
        """Let a bandwidth trace set the rate from now (`path=None` stops it)."""
        self.request(
            {
                "op": "trace",
                "direction": direction,
                "path": None if path is None else str(Path(path).resolve()),
                "format": format,
                "loop": loop,
            }
        )

    def capture(self, path: str | os.PathLike[str], label: str | None = None) -> None:
        """Write what the link delivers, both directions, to the pcapng file `path` (it
        appears under that name when `stop_capture` or `close` finishes it); its interfaces
        are "<label> uplink" and "<label> downlink" (default: the link's name)."""
        request = {"op": "capture", "link": self.name, "path": os.fspath(path)}
        self.request({**request, "label": label} if label else request)

    def stop_capture(self) -> dict[str, Any]:
        """Finish the capture: {path, packets: {direction: n}, dropped: {direction: n}}, or
        {} when none was running."""
        reply = self.request({"op": "capture", "link": self.name, "stop": True})
        return {k: v for k, v in reply.items() if k in ("path", "packets", "dropped")}

    def counters(self) -> dict[str, Any]:
        """Per direction: totals and per-stage counters; the link's RRC state and promotions
        (`rrc`, None without RRC states); plus the relay's own figures."""
        reply = self.request({"op": "counters"})
        reply.pop("ok", None)
        return reply
