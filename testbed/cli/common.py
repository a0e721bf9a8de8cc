"""What every verb of `testbed` shares: the exit codes, the one table that turns an error's type
into one, the options several verbs take, and the checks of --engine and its Ray options.

Exit codes mean the same thing for every verb:
  0  done as asked
  1  the run or the measurement failed (a node died, a link out of tolerance)
  2  bad input (scenario file, option, unknown run id, a folder that cannot be written)
  3  this host cannot do it (not root, a kernel feature or ROS 2 missing, a link rate beyond
     its relay)
  130 interrupted (Ctrl-C); everything created was removed
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from netem.errors import NetemError, ProfileError
from netem.traces import TraceError
from nodes.edgeloc.errors import EdgeLocError
from nodes.recording import RecordingError
from nodes.ros.env import RosEnvError
from nodes.ros.errors import RosError
from reports.errors import ReportError, ReportInputError
from testbed import console as con
from testbed.errors import BadInput, HostError, TestbedError

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_HOST, EXIT_INTERRUPTED = 0, 1, 2, 3, 130

#: The one place an error's type becomes an exit code: the first row whose type matches wins,
#: so the more specific types come first. Every package's error root is in it.
EXIT_CODES: tuple[tuple[type[Exception], int], ...] = (
    (BadInput, EXIT_BAD_INPUT),  # scenarios (ScenarioError), options, run ids
    (ProfileError, EXIT_BAD_INPUT),
    (TraceError, EXIT_BAD_INPUT),
    (ReportInputError, EXIT_BAD_INPUT),
    (RosEnvError, EXIT_BAD_INPUT),
    (HostError, EXIT_HOST),
    (TestbedError, EXIT_FAILED),
    (NetemError, EXIT_FAILED),
    (RecordingError, EXIT_FAILED),
    (ReportError, EXIT_FAILED),
    (EdgeLocError, EXIT_FAILED),
    (RosError, EXIT_FAILED),
)
#: What a verb turns into a message and an exit code instead of a traceback.
KNOWN_ERRORS = tuple(kind for kind, _ in EXIT_CODES)


def exit_code(err: BaseException) -> int:
    """The exit code `err` means (EXIT_CODES); 1 for anything else."""
    return next((code for kind, code in EXIT_CODES if isinstance(err, kind)), EXIT_FAILED)


ScenarioFile = Annotated[
    Path,
    typer.Argument(help="Scenario YAML file.", show_default=False, dir_okay=False, metavar="FILE"),
]
JsonFlag = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON.")]
RunsDir = Annotated[Path, typer.Option("--runs-dir", help="Where run folders go.", file_okay=False)]
HostsEngine = Annotated[
    str,
    typer.Option(
        "--engine",
        metavar="local|ray",
        help="local: this host only; ray: every host of topology.hosts, each on its own Ray "
        "node (the one offering the resource testbed-host-<name>; pip install '.[ray]').",
    ),
]
HostsAddress = Annotated[
    str,
    typer.Option(
        "--address",
        metavar="ADDRESS",
        help="--engine ray: the Ray cluster: auto (a running one) or HOST:PORT.",
    ),
]


def fail(err: BaseException) -> typer.Exit:
    """Print `err` as error lines; the typer.Exit of its exit code, for the verb to raise."""
    for line in str(err).splitlines():
        con.error(line)
    return typer.Exit(exit_code(err))


def check_engine(engine: str, ray_options: dict[str, tuple[str, str]]) -> None:
    """--engine is local or ray, and the options only Ray reads ({option: (value, default)})
    are left alone with local: a cluster address given to a local run was silently ignored."""
    if engine not in ("local", "ray"):
        raise fail(BadInput(f"--engine: expected local or ray, found {engine!r}"))
    given = [name for name, (value, default) in ray_options.items() if value != default]
    if engine == "local" and given:
        it = "it" if len(given) == 1 else "them"
        raise fail(
            BadInput(
                f"{', '.join(given)}: only --engine ray uses {it}; add --engine ray or leave "
                f"{it} out"
            )
        )
