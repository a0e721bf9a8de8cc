"""Fidelity: the emulated cell against published measurements of real 5G systems.

A case (`case`) is one measurement: the system's radio as its source configured it, the
source's probe and what it published. `testbed fidelity [CASE...]` sends the probe through
the relay in namespaces (`measure`), judges ours against theirs (`judge`: percentiles,
means, Wasserstein-1 and KS against the source's own samples (`data`), HARQ and segmentation
shares, floors) and writes JSON and a CDF figure per case (`runner`, `figure`). The same
probes through the link's stages on a fake clock (`model`) let the test suite judge a case
in a second.
"""

from testbed.fidelity.case import Case, FidelityError, Variant, find, library, load_case
from testbed.fidelity.judge import CaseResult
from testbed.fidelity.runner import run_cases, table, to_dict, write

__all__ = [
    "Case",
    "CaseResult",
    "FidelityError",
    "Variant",
    "find",
    "library",
    "load_case",
    "run_cases",
    "table",
    "to_dict",
    "write",
]
