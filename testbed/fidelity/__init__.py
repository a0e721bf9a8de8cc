"""Fidelity: the emulated cell against published measurements of real 5G systems.

A case (`case`) is one measurement: the system's radio as its source configured it, the
source's probe and what it published. `testbed fidelity [CASE...]` sends the probe through
the relay in namespaces (`measure`), judges ours against theirs (`judge`: percentiles,
means, Wasserstein-1 and KS against the source's own samples (`data`), HARQ and segmentation
shares, floors) and writes JSON and a CDF figure per case (`runner`, `figure`). The same
probes through the link's stages on a fake clock (`model`) let the test suite judge a case
in a second.

What the model leaves out, so each case says it where it matters:

- The UE's own processing (and, for the Ericsson trial, its TSN translators and core) is one
  constant per direction (`ue_delay_ul`, `ue_delay_dl`), calibrated on one variant or on the
  medians, and the case says on which.
- Where a source states no TDD pattern, uplink access or BLER, the case's are assumptions
  chosen by the data's shapes, marked as such beside each field.
- OpenAirInterface grants more PRBs when a backlog shows; the model keeps the configured grant,
  so EDAF's p90 comes out high (within tolerance, said in the case).
- A public network's rare long round trips (coverage gaps, cell changes) are not modelled:
  CICV5G's p99 is the figure that shows it.
- The srsRAN paper publishes means only, so that case judges means and floors.
- The relay's own cost on this host (a plain link's baseline, printed before each variant) is
  taken off every figure; W1's tolerance adds `judge.HOST_W1_MS` for what remains.

The data: DETERMINISTIC6G's histograms unchanged (CC BY-ND 4.0), EDAF's per-packet delays
(Apache-2.0) and CICV5G's round trips (CC BY 4.0) derived, each with its `SOURCE.md` in
`scenarios/fidelity/data/`.
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
