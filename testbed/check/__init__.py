"""Preflight and probes of this host's kernel, found by trying, never by reading lsmod.

Modules: `preflight` (`testbed check`: every capability a run needs, `run_checks`), `sandbox`
(the throwaway namespace the probes use, `probe_qdisc`), `netem_probe` (the runtime question
the `auto` link backend asks, cached per process), `leftovers` (what a killed check left, for
`testbed clean`).
"""

from testbed.check.leftovers import leftovers, remove_leftovers
from testbed.check.netem_probe import netem_available, netem_status
from testbed.check.preflight import REQUIRED, Check, CheckReport, run_checks
from testbed.check.sandbox import PROBE_PREFIX, QDISC_KINDS, Sandbox, probe_qdisc

__all__ = [
    "PROBE_PREFIX",
    "QDISC_KINDS",
    "REQUIRED",
    "Check",
    "CheckReport",
    "Sandbox",
    "leftovers",
    "netem_available",
    "netem_status",
    "probe_qdisc",
    "remove_leftovers",
    "run_checks",
]
