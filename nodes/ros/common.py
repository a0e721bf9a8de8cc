"""What every EdgeLoc node shares: its command line, the run's settings, its ROS lifecycle,
the JSON lines it logs and the stats file it writes at exit.

The settings are the replay's (`nodes.edgeloc.replay.ReplayConfig`, written as JSON by the
supervisor from the scenario through `testbed.nodesettings.replay_config`), so a real run and a
replay of the same scenario use the same learner, fusion, Kalman and gate settings.

Lifecycle (Jazzy aborts at exit otherwise, SPEC §8): our own SIGTERM/SIGINT handler sets a
stop flag; the node's loop ends; the executor thread is joined and the node destroyed before
`rclpy.shutdown()`.

A node runs alone (`python -m nodes.ros.<module>`: it owns the process, its rclpy context and
its signal handler, and logs on stdout) or as one role of a container (`nodes.ros.container`:
several nodes in one process). A role runs its module's `main(argv)` in a thread whose
`Composed` (a context variable, so the threads the role starts carry it too) gives it its own
log file, the container's stop flag and the container's rclpy context: `emit` writes to the
role's log, `ros_node` neither initialises nor shuts down rclpy (the container does, once), and
everything else a role does (its executor thread, stats, MCAP part) is what it does alone.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import contextvars
import faulthandler
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn, TextIO, TypeVar

from nodes.edgeloc.settings import REQUEST_TIMEOUT_S, ReplayConfig, config_from_dict
from nodes.recording.jsonfile import write_json
from nodes.ros.serving import parse_edges

#: Extra seconds of dataset beyond the scenario's duration: nodes start before the timeline.
DATASET_MARGIN_S = 60.0
#: The line every node logs once it is ready; the supervisor waits for it.
READY = "ready"
#: Exit status of a node whose recording failed (the supervisor then fails the run).
RECORDING_FAILED = 3
#: Seconds after SIGTERM at which a node still running dumps its threads' stacks: before the
#: supervisor's SIGKILL at 10 s (`testbed.supervisor.STOP_GRACE_S`).
STOP_DUMP_S = 8.0

T = TypeVar("T")


class _Parser(argparse.ArgumentParser):
    """A node's parser: alone, a refused command line exits (status 2) as argparse does; as a
    container's role it raises ValueError instead, so the reason lands in the role's own log
    (`call_main`), not in the container's shared stderr."""

    def error(self, message: str) -> NoReturn:
        if COMPOSED.get() is not None:
            raise ValueError(f"{self.prog}: {message}")
        super().error(message)


@dataclass(frozen=True)
class NodeArgs:
    """A node's command line: the run's settings file, whose node it is, where stats go."""

    config: ReplayConfig
    vehicle: str
    edge: str
    stats: Path | None
    events: Path | None
    timeout_s: float
    compute_cgroup: Path | None = None
    #: This process's MCAP part file (`testbed.recording`); None: record nothing.
    record: Path | None = None
    #: Also record camera frames (large; the scenario's `record.images`).
    record_images: bool = False
    #: With `edge: follow`: each gNB's edge server ({} asks `edge` always; `nodes.ros.serving`).
    edges: dict[str, str] = field(default_factory=dict)
    #: The vehicle sensor: wait for the run's common start time in this file (`nodes.ros.start`).
    start_file: Path | None = None
    #: The edge server: the vehicles it serves, one action each (`action_name`).
    serve: tuple[str, ...] = ()
    #: The sensor: the run's pre-rendered camera frames (`nodes.edgeloc.frames`).
    frames: Path | None = None

    @classmethod
    def parse(cls, argv: Sequence[str] | None = None, prog: str = "") -> NodeArgs:
        p = _Parser(prog=prog)
        p.add_argument("--config", required=True, help="the run's node settings (JSON)")
        p.add_argument("--vehicle", default="", help="the vehicle this node serves")
        p.add_argument("--edge", default="", help="the core/edge node serving the vehicle")
        p.add_argument("--stats", default=None, help="write a stats JSON here at exit")
        p.add_argument("--events", default=None, help="timeline events.jsonl to follow")
        p.add_argument(
            "--timeout", type=float, default=REQUEST_TIMEOUT_S, help="request timeout, seconds"
        )
        p.add_argument(
            "--compute-cgroup",
            default=None,
            help="cgroup v1 directory whose `tasks` the DNN compute thread joins (its CPU budget)",
        )
        p.add_argument(
            "--record",
            default=None,
            help="record every message this node publishes into this MCAP part file",
        )
        p.add_argument("--record-images", action="store_true", help="also record camera frames")
        p.add_argument(
            "--edges",
            default="",
            help="gnb=edge,...: ask the serving cell's edge server (edge: follow handovers)",
        )
        p.add_argument(
            "--start-file",
            default=None,
            help="the sensor: once its subscribers are there, wait for the run's start time "
            "(JSON {start_epoch_s}) in this file and publish frame 0 then",
        )
        p.add_argument(
            "--serve",
            default="",
            help="the edge server: the vehicles it serves (av1,av2,...), an action each",
        )
        p.add_argument(
            "--frames",
            default=None,
            help="the sensor: the drive's camera frames rendered ahead (nodes.edgeloc.frames)",
        )
        a = p.parse_args(argv)
        try:
            config = config_from_dict(json.loads(Path(a.config).read_text()))
        except (OSError, ValueError, TypeError) as err:
            p.error(f"cannot read node settings {a.config}: {err}")
        if not (math.isfinite(a.timeout) and a.timeout > 0):
            p.error(f"--timeout must be > 0 s, got {a.timeout}")
        try:
            edges = parse_edges(a.edges)
        except ValueError as err:
            p.error(str(err))
        return cls(
            config=config,
            vehicle=a.vehicle,
            edge=a.edge,
            stats=Path(a.stats) if a.stats else None,
            events=Path(a.events) if a.events else None,
            timeout_s=a.timeout,
            compute_cgroup=Path(a.compute_cgroup) if a.compute_cgroup else None,
            record=Path(a.record) if a.record else None,
            record_images=a.record_images,
            edges=edges,
            start_file=Path(a.start_file) if a.start_file else None,
            frames=Path(a.frames) if a.frames else None,
            serve=tuple(v for v in a.serve.split(",") if v),
        )


class ComputeThread:
    """The one thread a node runs its DNN stage on, so that stage alone can get a CPU budget.

    Started with a cgroup v1 directory, the thread writes its own thread id into that group's
    `tasks` file (v1 lets threads of one process sit in different cpu cgroups), so the CFS
    quota there throttles the DNN head or tail and nothing else: the node's other threads (ROS
    executor, the real-time VO/fusion processes) stay in the namespace's unthrottled group.
    Without a group, or when joining fails, jobs run unbudgeted and `budget` says why.

    A quota alone does not make a slow processor: at 0.007 cores the kernel grants 1 ms per
    143 ms period, so a 0.5 ms head runs at full speed and is rarely throttled, and the learner
    would see the vehicle as fast as the edge. So each job is also paced to the budget's speed:
    a job that used `c` s of this thread's CPU returns after `c / cores` s of wall time, as it
    would on a processor `cores` times as fast (the replay's latency model, `nodes.edgeloc.
    latency`). The quota stays the hard limit on throughput; the pacing gives jobs their latency.
    """

    def __init__(
        self,
        cgroup: Path | None,
        name: str = "dnn-compute",
        warmup: Callable[[], object] | None = None,
    ) -> None:
        self.cgroup = cgroup
        self.budget: dict[str, Any] = {"cgroup": str(cgroup) if cgroup else None, "joined": False}
        self.cores: float | None = None  # the budget's speed, once the thread joined its group
        self._warmup = warmup
        self._pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix=name, initializer=self._start
        )
        self._pool.submit(lambda: None).result()  # start it now: joining happens up front

    def _start(self) -> None:
        # `warmup` (one call of each stage) runs before the thread joins its group: a board
        # loads and warms its model before it drives, and torch's first call (62 ms of CPU
        # against 8 ms later here) would cost seconds under a budget of a few hundredths.
        if self._warmup is not None:
            t = time.perf_counter()
            self._warmup()
            self.budget["warmup_s"] = round(time.perf_counter() - t, 4)
        self._join()

    def _join(self) -> None:
        tid = threading.get_native_id()
        self.budget["tid"] = tid
        if self.cgroup is None:
            self.budget["reason"] = "no compute cgroup given (no CPU budget for this node)"
            return
        try:
            (self.cgroup / "tasks").write_text(f"{tid}\n")
        except OSError as err:
            self.budget["reason"] = f"cannot join {self.cgroup}/tasks: {err}"
            return
        self.budget["joined"] = True
        for name in ("cpu.cfs_quota_us", "cpu.cfs_period_us"):
            with contextlib.suppress(OSError, ValueError):
                self.budget[name] = int((self.cgroup / name).read_text())
        quota, period = (
            self.budget.get("cpu.cfs_quota_us", -1),
            self.budget.get("cpu.cfs_period_us"),
        )
        if quota > 0 and period:
            self.cores = quota / period
            self.budget["paced_cores"] = self.cores

    def run(self, fn: Callable[[], T]) -> tuple[T, float]:
        """Run `fn` on the compute thread, paced to the budget's speed (see the class);
        (its result, wall seconds it took there, pacing included)."""

        def timed() -> tuple[T, float]:
            t, cpu = time.perf_counter(), time.thread_time()
            out = fn()
            if self.cores is not None and self.cores < 1.0:
                due = t + (time.thread_time() - cpu) / self.cores
                time.sleep(max(0.0, due - time.perf_counter()))
            return out, time.perf_counter() - t

        return self._pool.submit(timed).result()

    def close(self) -> None:
        self._pool.shutdown(wait=True)


@dataclass(frozen=True)
class Composed:
    """What a role of a container shares with the container (see the module doc): its name
    (e.g. `av1.fusion`), its own log, and the container's stop flag."""

    name: str
    log: TextIO
    stop: Stop


#: Set in a container's role threads (and the threads they start); None in a node alone.
COMPOSED: contextvars.ContextVar[Composed | None] = contextvars.ContextVar(
    "edgeloc_composed", default=None
)


def log_stream() -> TextIO:
    """Where this node's lines go: its role's log in a container, else stdout."""
    composed = COMPOSED.get()
    return composed.log if composed is not None else sys.stdout


def start_thread(target: Callable[[], object], name: str) -> threading.Thread:
    """A daemon thread that runs `target` in a copy of the caller's context, so a role's
    threads log into the role's log (`threading.Thread` does not carry context variables)."""
    ctx = contextvars.copy_context()
    thread = threading.Thread(target=ctx.run, args=(target,), name=name, daemon=True)
    thread.start()
    return thread


def emit(event: str, **values: Any) -> None:
    """One JSON line in the node's log file (stdout alone, its role's log in a container):
    what the supervisor and tests read. The ready line also names the process's network
    namespace (inode) and pid, so a reader can check where each node ran, and in which
    process."""
    if event == READY:
        values["netns"] = os.stat("/proc/self/ns/net").st_ino
        values["pid"] = os.getpid()
        composed = COMPOSED.get()
        if composed is not None:
            values["role"] = composed.name
    line = json.dumps({"event": event, "t": round(time.time(), 6), **values})
    out = log_stream()
    # A role's log is shared by its threads: one write per line keeps lines whole.
    out.write(line + "\n")
    out.flush()


def write_stats(path: Path | None, stats: dict[str, Any]) -> None:
    """The node's counters at exit, written atomically (a reader never sees half a file)."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, stats)


def action_name(edge: str, vehicle: str) -> str:
    """The split-inference action one edge server offers one vehicle, e.g.
    `/core1/av1/split_inference`. One action per vehicle, not one per server: an action's
    status topic lists every goal its server holds and reaches every client, so with one
    shared action each of N vehicles took (and its downlink carried) the goals of all N, N^2
    goal states a second between them: with eight vehicles requests timed out waiting."""
    return f"/{edge}/{vehicle}/split_inference"


def to_stamp(t: float) -> Any:
    """A float of seconds (wall clock) as a builtin_interfaces/Time."""
    from builtin_interfaces.msg import Time

    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=min(round((t - sec) * 1e9), 999_999_999))


def from_stamp(stamp: Any) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


class Stop:
    """Set by SIGTERM/SIGINT: the node's loops poll it and end. One per process: a container
    makes it in its main thread (only there may Python install a signal handler) and hands it
    to every role."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.since = math.nan  # monotonic time of the signal (or of `set`)
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, frame: object) -> None:
        self.set()

    def set(self) -> None:
        """Stop, as a signal would (a container stops its other roles when one ends)."""
        if not self.event.is_set():
            self.since = time.monotonic()
            # A node still here just before the supervisor's SIGKILL writes where each of its
            # threads waits into its log: the only trace a hang at exit would leave.
            faulthandler.dump_traceback_later(STOP_DUMP_S, exit=False)
        self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def wait(self, seconds: float) -> bool:
        return self.event.wait(seconds)


class RecordedPublisher:
    """An rclpy publisher that also records each message it publishes (CDR bytes, logged at
    publish time) into the process's MCAP part. Publisher-side recording: no subscription, so
    recording adds no traffic to the emulated links."""

    def __init__(self, publisher: Any, topic: str, msg_type: type, recorder: Any) -> None:
        from rclpy.serialization import serialize_message

        from nodes.recording.schemas import type_name_of

        self._publisher, self.topic, self._recorder = publisher, topic, recorder
        self.type_name = type_name_of(msg_type)
        self._serialize = serialize_message

    def publish(self, msg: Any) -> None:
        self._publisher.publish(msg)
        if self._recorder is None:
            return
        try:
            self._recorder.write(self.topic, self.type_name, self._serialize(msg))
        except Exception as err:
            # Publishing may run on the executor thread, where an exception would only end
            # that thread: exit now, so the supervisor fails the run quoting this line.
            emit("error", message=f"recording {self.topic}: {err}")
            os._exit(RECORDING_FAILED)

    def get_subscription_count(self) -> int:
        return self._publisher.get_subscription_count()


class RosContext:
    """A running node: the rclpy node, the stop flag, what to destroy before the node, and
    the process's recorder (a `testbed.recording.PartWriter`, or None)."""

    def __init__(self, node: Any, stop: Stop, recorder: Any = None) -> None:
        self.node, self.stop, self.recorder = node, stop, recorder
        self._closers: list[Any] = []

    def publisher(
        self, msg_type: type, topic_name: str, depth: int, record: bool = True
    ) -> RecordedPublisher:
        """A publisher whose messages are recorded (unless `record` is False)."""
        pub = self.node.create_publisher(msg_type, topic_name, depth)
        return RecordedPublisher(pub, topic_name, msg_type, self.recorder if record else None)

    @property
    def recorded(self) -> dict[str, int]:
        """Messages recorded per topic so far (for the node's stats file)."""
        return dict(self.recorder.counts) if self.recorder is not None else {}

    def owns(self, entity: Any) -> Any:
        """Destroy `entity` (an action client/server) after the executor stopped; returns it."""
        self._closers.append(entity.destroy)
        return entity

    def close_entities(self) -> None:
        for close in reversed(self._closers):
            close()


@contextmanager
def ros_node(
    name: str, spin: bool = True, record: Path | None = None, events: bool = False
) -> Iterator[RosContext]:
    """An initialised rclpy context with one node, spun by an executor thread (if `spin`), and
    torn down in the order Jazzy needs whatever the body does: stop flag, executor thread
    joined, owned entities and the node destroyed, then `rclpy.shutdown()`; last, the MCAP
    part (`record`) is closed, after the last publish. `events=True` spins it on rclpy's
    EventsExecutor (`_executor`). In a container's role the context and
    the stop flag are the container's: the node gets its own executor and thread, and the
    container shuts rclpy down once every role has destroyed its node."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    from nodes.recording.parts import PartWriter

    composed = COMPOSED.get()
    recorder = PartWriter(record) if record is not None else None
    if composed is None:
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        stop = Stop()
    else:
        stop = composed.stop
    ctx = RosContext(rclpy.create_node(name), stop, recorder)
    executor = _executor(events)
    executor.add_node(ctx.node)
    thread = None
    if spin:

        def loop() -> None:
            while not stop:
                executor.spin_once(timeout_sec=0.1)

        thread = start_thread(loop, f"{name}-executor")
    try:
        yield ctx
    finally:
        # Each step is timed into the log: the supervisor kills a node that takes longer than
        # its grace to exit, and these figures say which step it was stuck in.
        steps: dict[str, float] = {}
        if math.isfinite(stop.since):  # signalled: how long the body took to notice
            steps["body"] = round(time.monotonic() - stop.since, 4)
        t = time.monotonic()

        def step(what: str) -> None:
            nonlocal t
            now = time.monotonic()
            steps[what] = round(now - t, 4)
            t = now

        stop.event.set()
        if thread is not None:
            thread.join(timeout=5)
        step("executor")
        ctx.close_entities()
        executor.remove_node(ctx.node)
        executor.shutdown()
        ctx.node.destroy_node()
        step("destroy")
        if composed is None:
            rclpy.shutdown()
            step("rclpy_shutdown")
        if recorder is not None:
            recorder.close()
            step("recording")
        emit("exit", seconds=steps)


#: Which executor spins a node: rclpy's pure-Python SingleThreadedExecutor, or for the nodes
#: that ask (`ros_node(events=True)`: the vehicle's fusion and inference nodes) its
#: EventsExecutor (C++, `rclpy.experimental`), unless EXECUTOR_ENV=single. The Python one
#: rebuilds its wait set on every wake-up, a large share of a vehicle's CPU at 20 Hz, and eight
#: vehicles needed more than a 2-core host had. Not for every node: with the experimental one
#: `tests/bench/bench_vehicles.py` printed 0.685 cores for the edge serving eight vehicles
#: (0.186 on the Python one), and the topic recorder never saw a message on subscriptions it
#: made after it started spinning.
EXECUTOR_ENV = "EDGELOC_EXECUTOR"


def _executor(events: bool) -> Any:
    if not events or os.environ.get(EXECUTOR_ENV) == "single":
        from rclpy.executors import SingleThreadedExecutor

        return SingleThreadedExecutor()
    from rclpy.experimental import EventsExecutor

    return EventsExecutor()


#: Diagnostic (bench_soak --trace-python): with this set to N seconds, a node traces its Python
#: allocations, snapshots them N s after start and, at exit, logs where the heap grew since.
TRACE_ENV = "EDGELOC_TRACEMALLOC_AFTER_S"


def _python_heap_tracer() -> Callable[[], None] | None:
    """Start tracing when TRACE_ENV is set; returns what logs the growth at exit."""
    after = os.environ.get(TRACE_ENV)
    if not after:
        return None
    try:
        delay_s = float(after)
    except ValueError:
        print(f"{TRACE_ENV}={after!r} is not seconds: not tracing", file=sys.stderr)
        return None
    import tracemalloc

    tracemalloc.start(4)  # frames per trace: enough to name the caller, cheap enough to stop
    first: list[Any] = []
    timer = threading.Timer(delay_s, lambda: first.append(tracemalloc.take_snapshot()))
    timer.daemon = True
    timer.start()

    def report() -> None:
        timer.cancel()
        if not first:
            tracemalloc.stop()
            return
        diff = tracemalloc.take_snapshot().compare_to(first[0], "traceback")
        tracemalloc.stop()
        grown = sum(d.size_diff for d in diff)
        print(f"python heap since {after} s: {grown / 1024:+.0f} kB", file=sys.stderr)
        for d in diff[:8]:
            print(f"  {d.size_diff / 1024:+.0f} kB in {d.count_diff:+d} blocks:", file=sys.stderr)
            for line in d.traceback.format()[-6:]:
                print(f"    {line}", file=sys.stderr)
        sys.stderr.flush()

    return report


def call_main(main: Callable[..., int], argv: Sequence[str] | None = None) -> int:
    """A node's `main(argv)` (argv None: the process's command line) as an exit status; a bad
    setting is one line in the node's log, not a trace."""
    try:
        return main() if argv is None else main(list(argv))
    except (ValueError, FileNotFoundError) as err:
        emit("error", message=str(err))
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 2


def run_main(main: Any) -> None:
    """Run a node's `main()` and exit with its status; a bad setting is one line, not a trace."""
    report_heap = _python_heap_tracer()
    code = call_main(main)
    if report_heap is not None:
        report_heap()
    sys.exit(code)
