"""Run state files: what each run may have created, written ahead so a crash leaves a list.

One JSON file per run in /run/edgeloc-testbed/ (or $EDGELOC_STATE_DIR). A resource is
recorded BEFORE it is created (processes right after they start; `clean` also finds those by
namespace), and every write is atomic (temp file + rename), so whatever instant a run is
killed at, its file names a superset of what exists. `down` and `clean` remove exactly what
a file lists.

Nouns:
- `ProcessRef`: a pid plus its start time (from /proc), so a reused pid is never mistaken
  for ours.
- `RunState`: one run's file: who owns it, its mode (`up` = left running detached, `run` =
  foreground), its phase (building | up | tearing-down), pool, namespaces, pids, cgroups.
- `liveness()`: 'live' (owner working on it), 'detached' (a finished `up`), 'dead' (its owner
  died while it still needed it: leftovers for `clean`).
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import json
import os
import re
import secrets
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from nodes.recording.jsonfile import write_json

DEFAULT_STATE_DIR = Path("/run/edgeloc-testbed")
STATE_DIR_ENV = "EDGELOC_STATE_DIR"
RUN_ID_RE = re.compile(r"^[0-9a-f]{6}$")

Mode = Literal["up", "run"]
Phase = Literal["building", "up", "tearing-down"]
Liveness = Literal["live", "detached", "dead"]


def state_dir() -> Path:
    return Path(os.environ.get(STATE_DIR_ENV) or DEFAULT_STATE_DIR)


def proc_start_time(pid: int) -> int | None:
    """Start time of a process in clock ticks since boot (field 22 of /proc/PID/stat), or None
    when it does not exist or is a zombie (already dead, only waiting to be reaped)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            data = f.read()
    except OSError:
        return None
    # comm (field 2) may contain spaces and parentheses: split after its last ')'.
    fields = data[data.rindex(b")") + 2 :].split()
    if fields[0] == b"Z":
        return None
    return int(fields[19])


@dataclass(frozen=True)
class ProcessRef:
    """A process we started, identified by pid AND start time (pids get reused)."""

    pid: int
    start: int
    what: str = ""

    @classmethod
    def of(cls, pid: int, what: str = "") -> ProcessRef:
        start = proc_start_time(pid)
        return cls(pid, start if start is not None else -1, what)

    def alive(self) -> bool:
        """Still the very process we recorded (not a newer one with the same pid)."""
        return self.start >= 0 and proc_start_time(self.pid) == self.start


@dataclass
class RunState:
    """One run's state file (see the module docstring for the fields' meaning)."""

    run_id: str
    scenario: str
    scenario_path: str | None
    owner: ProcessRef
    mode: Mode
    phase: Phase
    pool: str | None
    started: float
    namespaces: list[str] = field(default_factory=list)
    pids: list[ProcessRef] = field(default_factory=list)
    cgroups: list[str] = field(default_factory=list)
    version: int = 1
    #: The run's results folder (`runs/<id>`), once made: `clean` finalises its recording.
    folder: str | None = None
    #: Whether the run may have VXLAN tunnels here (links across hosts): `down` then looks
    #: for them in each namespace. True where a file does not say (an older one).
    vxlan: bool = True

    # ---- file --------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        return state_dir() / f"{self.run_id}.json"

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["owner"] = asdict(self.owner)
        d["pids"] = [asdict(p) for p in self.pids]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RunState:
        return cls(
            run_id=str(d["run_id"]),
            scenario=str(d.get("scenario", "?")),
            scenario_path=d.get("scenario_path"),
            owner=ProcessRef(**d["owner"]),
            mode=d.get("mode", "run"),
            phase=d.get("phase", "building"),
            pool=d.get("pool"),
            started=float(d.get("started", 0.0)),
            namespaces=[str(n) for n in d.get("namespaces", [])],
            pids=[ProcessRef(**p) for p in d.get("pids", [])],
            cgroups=[str(c) for c in d.get("cgroups", [])],
            version=int(d.get("version", 1)),
            folder=d.get("folder"),
            vxlan=bool(d.get("vxlan", True)),
        )

    def save(self) -> None:
        """Atomic write: a reader (or a crash) sees the old file or the new one, never half.
        No fsync: the directory is on tmpfs (/run) and a SIGKILL does not lose page cache."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_json(self.path, self.to_dict())  # temp name `.<id>.json.<pid>.tmp`, as clean expects

    def delete(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()

    # ---- write-ahead records -----------------------------------------------------------

    def record_namespaces(self, names: list[str]) -> None:
        self.namespaces += [n for n in names if n not in self.namespaces]
        self.save()

    def record_pid(self, ref: ProcessRef) -> None:
        self.pids.append(ref)
        self.save()

    def record_cgroup(self, path: str) -> None:
        if path not in self.cgroups:
            self.cgroups.append(path)
            self.save()

    def record_folder(self, folder: Path) -> None:
        self.folder = str(Path(folder).resolve())
        self.save()

    def set_phase(self, phase: Phase) -> None:
        self.phase = phase
        self.save()

    # ---- reading -----------------------------------------------------------------------

    def owner_alive(self) -> bool:
        return self.owner.alive()

    def liveness(self) -> Liveness:
        if self.mode == "up" and self.phase == "up":
            return "detached"  # a finished `testbed up`: nobody needs to be alive for it
        return "live" if self.owner_alive() else "dead"

    def started_text(self) -> str:
        return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started))

    def describe(self) -> dict[str, Any]:
        d = self.to_dict()
        d["liveness"] = self.liveness()
        d["started_text"] = self.started_text()
        d["state_file"] = str(self.path)
        return d


def new_run(
    scenario: str,
    scenario_path: str | None,
    mode: Mode,
    run_id: str,
    pool: str | None,
    vxlan: bool = True,
) -> RunState:
    return RunState(
        vxlan=vxlan,
        run_id=run_id,
        scenario=scenario,
        scenario_path=scenario_path,
        owner=ProcessRef.of(os.getpid(), "owner"),
        mode=mode,
        phase="building",
        pool=pool,
        started=time.time(),
    )


def load_run(run_id: str) -> RunState | None:
    path = state_dir() / f"{run_id}.json"
    try:
        return RunState.from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        return None


def list_runs() -> list[RunState]:
    """Every run with a state file, oldest first. Unreadable files are skipped (a file is only
    ever replaced whole, so that means someone else's file, not ours)."""
    runs = []
    directory = state_dir()
    if not directory.is_dir():
        return []
    for path in directory.glob("*.json"):
        if not RUN_ID_RE.match(path.stem):
            continue
        try:
            runs.append(RunState.from_dict(json.loads(path.read_text())))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return sorted(runs, key=lambda r: r.started)


def fresh_run_id(taken: set[str], key: Callable[[str], object] | None = None) -> str:
    """6 lowercase hex chars that no state file and no `taken` id uses.

    With `key` (e.g. the ROS domain id of a run id) the new id also differs from every taken
    id under `key`, as long as such an id exists (`key` values are tried for 10000 draws).
    """
    avoid = {key(t) for t in taken} if key is not None else set()
    for attempt in itertools.count():
        run_id = secrets.token_hex(3)
        if run_id in taken or (state_dir() / f"{run_id}.json").exists():
            continue
        if key is None or key(run_id) not in avoid or attempt >= 10_000:
            return run_id
    raise AssertionError("unreachable")


@contextlib.contextmanager
def locked() -> Iterator[None]:
    """Serialise choosing a pool + writing the first state file between concurrent builds."""
    directory = state_dir()
    directory.mkdir(parents=True, exist_ok=True)
    fd = os.open(directory / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)
