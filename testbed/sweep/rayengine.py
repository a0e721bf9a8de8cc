"""A sweep's runs as Ray tasks (`testbed sweep --engine ray`): an existing distributed engine,
not a scheduler of our own.

Each `Job` (a variant with one seed) is one task, run on a worker host by the same code a local
sweep runs (`engines.run_job`), in a temporary folder there; the task sends back its rows and
its folder as a tar archive, which lands under the sweep's `--out` here (`runs/<id>/` of a real
run with its run.mcap, summary.json and report, or `replay/<name>/`). A real run asks for one
unit of a custom resource (`testbed`, settable: give each testbed host one, and two real-time
runs never share a host); a replay asks for one CPU. A real run that fails is retried once, on
another host of the cluster when there is one; its row then says so. Ctrl-C cancels every task
and runs `testbed clean`'s removal of dead runs on each host that ran one, then stops the sweep
(exit 130).

Hosts need root for real runs, this checkout at the same path and its venv (with `pip install
'.[ray]'`).

How to start a cluster (each host: root, this checkout at the same path, its venv with Ray):
  sudo .venv/bin/ray start --head --resources='{"testbed": 1}'               # first host
  sudo .venv/bin/ray start --address=HEAD:6379 --resources='{"testbed": 1}'  # every other host
`--address auto` (default) finds the running cluster, `HOST:PORT` names one, `local` starts a
one-host cluster for this sweep alone. A retried run's row in sweep.json names the host (`host`)
and says `attempts: 2`, and the sweep then removes what the dead run left on every host still in
the cluster. Each real run runs in a process of its own, forked from a server that the Ray worker
starts with the run's modules, its report and torch imported once, and dies with the worker.

Recent Ray (2.60 is what `make test` installs) turns token authentication on for a new local
cluster and saves the token in ~/.ray/auth_token; a `ray start` on a host that has that file
then requires it. Copy the head's file to every host (or set RAY_AUTH_TOKEN); the sweep sends it
when it finds one, as `ray start` does, and says so when the cluster refuses it (exit 3).
RAY_AUTH_MODE=disabled on every host and on the sweep turns it off.

Cost (`make bench BENCH=ray`, per task against the local loop, one job at a time, goal 2 s; 2-core
VM, host otherwise idle): +0.07 s and -0.01 s per offline replay (8 replays of 4 s); per real run
(2 runs of 4 s) +2.19, +2.07, +1.75, +1.54 and +1.01 s in five measurements (local 22-24 s, Ray
25-28 s), so the goal is met in three of five. The first run on a worker still waits for the
server's imports (1.97 s in a fresh interpreter, the benchmark's last line), so a sweep with more
runs per worker pays less per run; starting an interpreter per real run instead cost +3.1 to
+3.5 s. The tests start a head and a worker node on one machine and kill the worker mid-run.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import tarfile
import tempfile
import time
from collections.abc import Iterator, MutableMapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from testbed.errors import BadInput, HostError
from testbed.state import ProcessRef
from testbed.sweep.jobs import Job, Progress, run_job
from testbed.sweep.output import VariantResult, row_line

#: `--address local`: start a one-host Ray cluster in this process (and stop it at the end).
LOCAL = "local"
#: How long a cleaning task per host may take after Ctrl-C.
CLEAN_TIMEOUT_S = 60.0
#: A task's temporary folder on its host, and the file in it that names the worker.
TASK_PREFIX = "edgeloc-sweep-"
OWNER_FILE = ".owner"


@dataclass(frozen=True)
class RayOptions:
    """Where the cluster is (`auto`: a running one found by Ray; `local`; or HOST:PORT) and
    the custom resource a real run asks one unit of."""

    address: str = "auto"
    resource: str = "testbed"


def _ray() -> Any:
    try:
        import ray
    except ImportError:
        raise HostError(
            "--engine ray needs Ray in this interpreter: pip install '.[ray]' (or ray>=2.9)"
        ) from None
    return ray


def connect(options: RayOptions, how_to_start: str | None = None) -> tuple[Any, bool]:
    """Ray, connected to the cluster; and whether this process started it (`local`).

    `how_to_start` replaces the sweep's advice in the error for a cluster that is not there
    (`testbed up --engine ray` wants other resources on its hosts than a sweep)."""
    ray = _ray()
    if ray.is_initialized():
        return ray, False
    try:
        if options.address == LOCAL:
            # One host: it holds one unit of the resource, as a `ray start` of a host would.
            # Ray's "local" starts a new cluster even where `ray start` left one's address.
            ray.init(
                address="local",
                resources={options.resource: 1},
                include_dashboard=False,
                logging_level="ERROR",
                log_to_driver=False,
            )
            return ray, True
        _reachable(options.address)
        if token_auth_if_token():
            # Ray read RAY_AUTH_MODE at import; this is how `ray start` makes it read it again.
            with contextlib.suppress(ImportError, AttributeError):
                from ray._raylet import Config

                Config.initialize("")
        ray.init(address=options.address, logging_level="ERROR", log_to_driver=False)
    except ConnectionError as err:
        if _token_refused(err):
            raise HostError(
                f"the Ray cluster at {options.address!r} wants a token this host did not send "
                "or it refused: copy the head's ~/.ray/auth_token here (or set RAY_AUTH_TOKEN), "
                "and leave RAY_AUTH_MODE unset or 'token'"
            ) from None
        if how_to_start is None:
            how_to_start = (
                f"start one with `ray start --head --resources='{{\"{options.resource}\": 1}}'`"
                " on a testbed host (see the README), or use --address local for this host alone"
            )
        raise HostError(f"no Ray cluster at {options.address!r} ({err}); {how_to_start}") from None
    return ray, False


def token_auth_if_token(
    environ: MutableMapping[str, str] | None = None, home: Path | None = None
) -> bool:
    """Turn Ray's token authentication on for this process when a token is at hand and
    RAY_AUTH_MODE says nothing, as `ray start` does for the hosts: a head started where a
    token exists (Ray saves one in ~/.ray at the first local cluster) refuses a driver that
    sends none. Returns whether it is on."""
    env = os.environ if environ is None else environ
    if "RAY_AUTH_MODE" in env:
        return env["RAY_AUTH_MODE"].lower() == "token"
    path = env.get("RAY_AUTH_TOKEN_PATH") or str((home or Path.home()) / ".ray" / "auth_token")
    if env.get("RAY_AUTH_TOKEN") or Path(path).is_file():
        env["RAY_AUTH_MODE"] = "token"
        return True
    return False


def _token_refused(err: BaseException | None) -> bool:
    """Whether Ray's failure to connect was, underneath, its authentication."""
    while err is not None:
        if type(err).__name__ == "AuthenticationError" or "InvalidAuthToken" in str(err):
            return True
        err = err.__cause__ or err.__context__
    return False


def _reachable(address: str) -> None:
    """Fail fast on a HOST:PORT nobody listens at (Ray itself retries for a minute)."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return  # `auto` and the like: Ray finds the cluster (or says there is none) at once
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=5).close()
    except OSError as err:
        raise ConnectionError(f"{address}: {err}") from None


def _pack(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        if folder.exists():
            tar.add(folder, arcname=".")
    return buf.getvalue()


def _unpack(data: bytes, into: Path) -> None:
    into.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        tar.extractall(into, filter="data")


_ENGINES: list[Any] = []


def _engine() -> Any:
    """This worker's replay engine, kept between tasks (its model and DNN outputs are shared
    by the variants that drive the same frames, as in a local sweep)."""
    from testbed.sweep.jobs import _ReplayEngine

    if not _ENGINES:
        _ENGINES.append(_ReplayEngine())
    return _ENGINES[0]


def execute(job: Job, real: bool) -> tuple[list[VariantResult], bytes, str, list[str]]:
    """The task: run `job` in a temporary folder on this host; its rows (folders relative to
    that folder), the folder as tar.gz, this host's address and the run's progress lines."""
    import socket

    tmp = Path(tempfile.mkdtemp(prefix=TASK_PREFIX))
    lines: list[str] = []
    try:
        # Whose folder this is: a worker killed mid-run cannot remove it, `clean_host` can.
        me = ProcessRef.of(os.getpid(), "sweep task")
        (tmp / OWNER_FILE).write_text(f"{me.pid} {me.start}\n")
        variant_file = tmp / "variants" / f"{job.name}.yaml"
        variant_file.parent.mkdir(parents=True)
        variant_file.write_text(job.text)
        here = replace(job, scenario=replace(job.scenario, source=variant_file))
        if real:
            rows = _run_apart(here, tmp, lines)
        else:
            rows = run_job(here, False, tmp, lines.append, _engine())
        for r in rows:
            if r.folder:
                with contextlib.suppress(ValueError):
                    r.folder = str(Path(r.folder).resolve().relative_to(tmp.resolve()))
        return rows, _pack(tmp / ("runs" if real else "replay")), socket.gethostname(), lines
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


#: What the process that forks each real run imports once, before its first run: the run, its
#: report and the replay the report calls (torch). A fresh interpreter per run paid them every
#: time (`make bench BENCH=ray` prints how long: about 2.2 s here, more than the engine's 2-s
#: goal for its whole cost per task).
RUN_PRELOAD = ["testbed.run", "reports.build", "nodes.edgeloc.replay", __name__]
#: Where a real run's child leaves its answer and its progress lines, in the task's folder
#: (hidden, and outside the runs/ that goes back to the sweep).
ANSWER_FILE = ".answer.pickle"
PROGRESS_FILE = ".progress.log"


def _forkserver() -> Any:
    """This worker's multiprocessing context whose server preloads `RUN_PRELOAD` (the server
    starts with the first real run, and ends once the worker and its runs have)."""
    import multiprocessing

    context = multiprocessing.get_context("forkserver")  # one per process
    context.set_forkserver_preload(RUN_PRELOAD)
    return context


@contextlib.contextmanager
def _no_main_module() -> Iterator[None]:
    """Hide this process's `__main__` while a child is started: multiprocessing re-runs the
    parent's main script in each child, and a Ray worker's is Ray's worker script, which
    would import Ray into every run (the very thing the fork server keeps out)."""
    import sys
    import types

    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


def _run_apart(job: Job, tmp: Path, lines: list[str]) -> list[VariantResult]:
    """A real run in a process of its own, forked from a server with the run's modules loaded.

    Not in the worker itself, nor in a fork of it: building namespaces forks (pyroute2), and a
    forked copy of a Ray worker that is sent SIGTERM runs Ray's exit in the copy, which makes the
    raylet kill the worker mid-run (seen as WorkerCrashedError in about one run in three on a
    busy host). The fork server is a fresh interpreter that never imports Ray; the run dies
    with this worker (`_die_with_worker`), and `testbed clean` removes what it left."""
    import pickle

    answer, log = tmp / ANSWER_FILE, tmp / PROGRESS_FILE
    child = _forkserver().Process(
        target=_run_here, args=(job, tmp, answer, log), name=f"testbed run {job.name}"
    )
    try:
        with _no_main_module():
            child.start()
    except (OSError, EOFError) as err:  # the server died while loading RUN_PRELOAD
        # Not a HostError, which would stop the sweep: the run is retried on another host.
        raise RuntimeError(
            f"the process that starts real runs on this host failed ({type(err).__name__}: "
            f"{err}); the Ray worker's log (under /tmp/ray/session_latest/logs) says why"
        ) from None
    try:
        while child.exitcode is None:  # in steps: a cancel must not wait for the run's end
            child.join(0.5)
    except BaseException:  # a cancelled task: the run stops as if its worker had died
        child.kill()
        child.join()
        raise
    with contextlib.suppress(OSError):
        lines += log.read_text(errors="replace").splitlines()
    if child.exitcode != 0 or not answer.is_file():
        code = child.exitcode
        how = f"was killed by signal {-code}" if code is not None and code < 0 else f"exited {code}"
        tail = "; ".join(x for x in lines[-5:] if x.strip())
        raise RuntimeError(f"the run's process {how}: {tail}")
    kind, value = pickle.loads(answer.read_bytes())
    if kind == "raise":
        raise value
    return value  # type: ignore[no-any-return]


def _die_with_worker() -> None:
    """Kill this process (a run forked by the fork server) the moment the worker that started
    it is gone, however it went. The fork server outlives the worker while any of its children
    runs, so its death, which `die_with_parent` would catch, never comes first; the worker's
    own end of a pipe (multiprocessing's parent sentinel) closes with the worker."""
    import multiprocessing
    import select
    import signal
    import threading

    parent = multiprocessing.parent_process()
    if parent is None:
        return
    sentinel = parent.sentinel

    def watch() -> None:
        select.select([sentinel], [], [])
        os.kill(os.getpid(), signal.SIGKILL)  # as the old child's parent-death signal did

    if select.select([sentinel], [], [], 0)[0]:  # gone before this child got here
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=watch, name="die with the Ray worker", daemon=True).start()


def _run_here(job: Job, tmp: Path, answer: Path, log: Path) -> None:
    """The forked child: one real run; its progress (and anything it prints) into `log`, its
    pickled rows (or the BadInput/HostError it raised) into `answer`."""
    import pickle
    import sys

    _die_with_worker()
    out_fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(out_fd, 1)
    os.dup2(out_fd, 2)
    os.close(out_fd)

    def say(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    try:
        out: tuple[str, Any] = ("rows", run_job(job, True, tmp, say))
    except (BadInput, HostError) as err:
        out = ("raise", err)
    answer.write_bytes(pickle.dumps(out))


class _Board:
    """A rich progress display, one line per job with its state, in a terminal; nothing (the
    sweep's plain progress lines) in CI or a pipe."""

    MAX_LINES = 30  # beyond this many jobs, one line for all of them

    def __init__(self, jobs: list[Job]) -> None:
        from testbed import console

        self.live = not console.is_plain()
        self.bar: Any = None
        self.rows: dict[str, Any] = {}
        self.total: Any = None
        if not self.live:
            return
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(
            TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
            console=console.out,
        )  # fmt: skip
        if len(jobs) <= self.MAX_LINES:
            for job in jobs:
                self.rows[job.name] = self.bar.add_task(f"{job.title}: queued", total=1)
        self.total = self.bar.add_task(f"sweep: 0/{len(jobs)} done", total=len(jobs))

    def __enter__(self) -> _Board:
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def print(self, text: str) -> None:
        self.bar.console.print(text, markup=False, highlight=False)

    def state(self, job: Job, text: str, done: bool = False) -> None:
        if self.bar is None:
            return
        if job.name in self.rows:
            self.bar.update(self.rows[job.name], description=f"{job.title}: {text}",
                            completed=1 if done else 0)  # fmt: skip
        if done:
            self.bar.advance(self.total)
            n = int(self.bar.tasks[self.total].completed)
            self.bar.update(
                self.total, description=f"sweep: {n}/{self.bar.tasks[self.total].total:g} done"
            )


def clean_host() -> tuple[str, str]:
    """The cleaning task: `testbed clean` on this host (dead runs' leftovers), in its own
    process for the reason `_run_apart` gives."""
    import socket
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "testbed.cli", "clean"],
        capture_output=True,
        text=True,
        env={**os.environ, "CI": "1"},
        timeout=CLEAN_TIMEOUT_S,
        check=False,
    )
    said = [x for x in (done.stdout + done.stderr).splitlines() if x.strip()]
    gone = remove_dead_task_folders(Path(tempfile.gettempdir()))
    if gone:
        said.append(f"{gone} folder(s) of dead sweep tasks removed")
    return socket.gethostname(), "; ".join(said[-3:]) or f"testbed clean: exit {done.returncode}"


def remove_dead_task_folders(where: Path) -> int:
    """Remove the temporary folders of sweep tasks whose worker is gone; how many."""
    gone = 0
    for folder in where.glob(f"{TASK_PREFIX}*"):
        try:
            pid, start = (int(x) for x in (folder / OWNER_FILE).read_text().split())
        except (OSError, ValueError):
            continue  # not one of ours, or not yet marked: leave it
        if not ProcessRef(pid, start).alive():
            shutil.rmtree(folder, ignore_errors=True)
            gone += 1
    return gone


def run_on_ray(
    jobs: list[Job], real: bool, out: Path, progress: Progress, options: RayOptions
) -> list[VariantResult]:
    """Run every job as a Ray task; their rows in job order (see the module doc)."""
    ray, started = connect(options)
    try:
        return _Sweep(ray, jobs, real, out, progress, options).run()
    finally:
        if started:
            ray.shutdown()


class _Sweep:
    def __init__(
        self,
        ray: Any,
        jobs: list[Job],
        real: bool,
        out: Path,
        progress: Progress,
        options: RayOptions,
    ) -> None:
        self.ray, self.jobs, self.real, self.out = ray, jobs, real, out
        self.progress, self.options = progress, options
        resources = ray.cluster_resources()
        if real and resources.get(options.resource, 0) < 1:
            raise HostError(
                f"the Ray cluster has no {options.resource!r} resource: no host may run a "
                f'real run (start each testbed host with --resources=\'{{"{options.resource}"'
                ": 1}')"
            )
        self.task = ray.remote(execute)
        self.hosts_used: set[str] = set()
        self.deaths = 0  # tasks whose worker or host died under them
        self.board: _Board

    def _submit(self, job: Job, avoid: str | None = None) -> Any:
        opts: dict[str, Any] = {"max_retries": 0}
        if self.real:
            opts.update(num_cpus=0, resources={self.options.resource: 1})
        else:
            opts.update(num_cpus=1)
        other = self._other_node(avoid) if avoid else None
        if other is not None:
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            opts["scheduling_strategy"] = NodeAffinitySchedulingStrategy(other, soft=True)
        return self.task.options(**opts).remote(job, self.real)

    def _other_node(self, hostname: str) -> str | None:
        """A live node of the cluster, holding the resource, on another host than `hostname`."""
        for node in self.ray.nodes():
            if not node.get("Alive"):
                continue
            if self.real and node.get("Resources", {}).get(self.options.resource, 0) < 1:
                continue
            if node.get("NodeManagerHostname") != hostname:
                return str(node["NodeID"])
        return None

    def run(self) -> list[VariantResult]:
        with _Board(self.jobs) as board:
            self.board = board
            return self._run()

    def _say(self, text: str) -> None:
        self.board.print(text) if self.board.live else self.progress(text)

    def _run(self) -> list[VariantResult]:
        pending = {self._submit(job): (job, 1) for job in self.jobs}
        results: dict[int, list[VariantResult]] = {}
        t0 = time.perf_counter()
        try:
            while pending:
                ready, _ = self.ray.wait(list(pending), num_returns=1, timeout=5.0)
                if not ready:
                    if not self.board.live:
                        self.progress(
                            f"  {len(results)}/{len(self.jobs)} done, {len(pending)} queued or "
                            f"running ({time.perf_counter() - t0:.0f} s)"
                        )
                    continue
                ref = ready[0]
                job, attempt = pending.pop(ref)
                died = False
                try:
                    rows, archive, host, lines = self.ray.get(ref)
                except (BadInput, HostError):
                    raise
                except Exception as err:  # the task itself died (its host, its worker)
                    rows, archive, host, lines = self._lost(job, err), b"", "?", []
                    died = True
                    self.deaths += 1
                self.hosts_used.add(host)
                failed = any(r.error for r in rows)
                # A real run that failed, or any task whose host or worker died, runs again
                # once (a replay that fails would fail the same way anywhere).
                if failed and (self.real or died) and attempt == 1:
                    where = "its Ray task died" if died else f"failed on {host}"
                    self._say(f"{job.title}: {where}; retrying once elsewhere")
                    if died:
                        self._say(f"  {rows[0].error}")
                    self.board.state(job, f"retrying ({where})")
                    pending[self._submit(job, avoid=host)] = (job, 2)
                    continue
                self._land(rows, archive)
                for r in rows:
                    r.host, r.attempts = host, attempt
                    if attempt == 2 and r.error:
                        r.error += " (after a retry)"
                results[self.jobs.index(job)] = rows
                self.board.state(job, f"{'failed' if failed else 'done'} on {host}", done=True)
                self._say(f"{job.title}: on {host}")
                for r in rows:
                    self._say(f"  {r.vehicle}: {row_line(r)}")
                if failed:
                    for x in [x for x in lines if x.strip()][-5:]:
                        self._say(f"    {x.strip()}")
        except KeyboardInterrupt:
            self._cancel(list(pending))
            raise
        if self.real and self.deaths:
            # A run whose worker died was killed mid-way: its namespaces and nodes are still up
            # wherever its host still is.
            self._say(f"{self.deaths} task(s) died mid-run: cleaning the hosts")
            self._clean_hosts()
        return [r for i in range(len(self.jobs)) for r in results.get(i, [])]

    def _lost(self, job: Job, err: Exception) -> list[VariantResult]:
        from testbed.sweep.jobs import _failed_row

        why = f"the Ray task died: {type(err).__name__}: {str(err).splitlines()[0][:200]}"
        rows = [
            _failed_row(job.index, job.values, v.name, why) for v in job.scenario.edgeloc_vehicles()
        ]
        for r in rows:
            r.seed = job.seed
        return rows

    def _land(self, rows: list[VariantResult], archive: bytes) -> None:
        """Unpack a task's folder under `out` and point its rows at where it landed."""
        where = self.out / ("runs" if self.real else "replay")
        if archive:
            _unpack(archive, where)
        for r in rows:
            if r.folder and not Path(r.folder).is_absolute():
                r.folder = str(
                    where / Path(r.folder).relative_to("runs" if self.real else "replay")
                )

    def _cancel(self, refs: list[Any]) -> None:
        """Ctrl-C: cancel every task, then remove what killed runs left on each host."""
        self._say(f"interrupted: cancelling {len(refs)} task(s) and cleaning the hosts")
        for ref in refs:
            with contextlib.suppress(Exception):
                self.ray.cancel(ref, force=True)
        if not self.real:
            return
        # A cancelled run's worker must be gone before its run counts as dead to `clean`.
        with contextlib.suppress(Exception):
            self.ray.wait(refs, num_returns=len(refs), timeout=15.0)
        self._clean_hosts()

    def _clean_hosts(self) -> None:
        """`testbed clean`'s removal of dead runs, on every live node of the cluster."""
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        cleaner = self.ray.remote(clean_host)
        refs_clean = [
            cleaner.options(
                num_cpus=0,
                scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False),
            ).remote()
            for n in self.ray.nodes()
            if n.get("Alive")
        ]
        deadline = time.monotonic() + CLEAN_TIMEOUT_S
        for ref in refs_clean:  # one by one: a node that just died must not hide the others
            try:
                host, text = self.ray.get(ref, timeout=max(1.0, deadline - time.monotonic()))
            except Exception as err:
                self._say(f"  a host could not be cleaned ({type(err).__name__}): run "
                          "`testbed clean` there")  # fmt: skip
            else:
                self._say(f"  {host}: {text}")
