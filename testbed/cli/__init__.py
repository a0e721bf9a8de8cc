"""`testbed`: the command line. Verbs read as sentences; the work lives in other modules, and
each verb module here only parses, calls that work and prints it. The verbs, by group:

  scenario  validate, schema: scenario files before anything is built
  lab       up, exec, env, status, down, clean: a network left up, and what runs leave
  run       run, report: a whole experiment, and its report rebuilt from run.mcap
  replay    replay: the EdgeLoc workload in one process, no network
  sweep     sweep: a grid of variants of a scenario, one comparison
  checks    check, link-test: what this host and a scenario's links can do
  fidelity  fidelity: the emulated cell against published measurements of real cells

What every verb shares (the exit codes and the error table that decides them, the common
options) is in `testbed.cli.common`.
"""

from __future__ import annotations

import sys

import typer

from testbed import console as con
from testbed.cli import checks, fidelity, lab, replay, run, scenario, sweep
from testbed.cli.common import EXIT_INTERRUPTED

app = typer.Typer(
    name="testbed",
    help=(
        "Emulate a 5G UE-gNB-core network in Linux namespaces and run EdgeLoc over it.\n\n"
        "Typical session:\n\n"
        "  testbed check                      # can this host run it?\n\n"
        "  testbed validate scenarios/*.yaml  # are my scenarios right?\n\n"
        "  testbed up scenarios/default.yaml  # build the network, leave it up\n\n"
        "  testbed status ; testbed down      # see it, tear it down\n\n"
        "  testbed run scenarios/default.yaml # the whole experiment\n\n"
        "  testbed report runs/<id>           # rebuild its report from run.mcap\n\n"
        "  testbed sweep FILE --set KEY=A,B   # a grid of variants, one comparison"
    ),
    epilog=(
        "Exit codes, the same for every command: 0 done as asked; 1 the run or the "
        "measurement failed (a node died, a link out of tolerance); 2 bad input (a scenario "
        "file, an option, an unknown run id, a folder that cannot be written); 3 this host "
        "cannot do it (not root, a kernel feature or ROS 2 missing, a link rate beyond its "
        "relay); 130 interrupted (Ctrl-C), everything created removed."
    ),
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
)

# The help lists the verbs in this order, a session's, which crosses the groups.
app.command()(scenario.validate)
app.command()(scenario.schema)
app.command()(lab.up)
app.command()(run.run)
app.command()(run.report)
app.command()(replay.replay)
app.command()(sweep.sweep)
app.command("link-test")(checks.link_test)
app.command()(fidelity.fidelity)
app.command(
    "exec",
    context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
)(lab.exec_)
app.command("env")(lab.env_)
app.command()(lab.down)
app.command()(lab.status)
app.command()(lab.clean)
app.command()(checks.check)


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:
        con.error("interrupted")
        sys.exit(EXIT_INTERRUPTED)
