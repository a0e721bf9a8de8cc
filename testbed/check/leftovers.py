"""What a `testbed check` killed mid-way (SIGKILL, power loss) left: sandbox namespaces and cgroup
trees named with PROBE_PREFIX, found and removed by `testbed clean`."""

from __future__ import annotations

import os

from netem.netns import NETNS_DIR
from testbed import cgroups
from testbed.check.sandbox import PROBE_PREFIX

# ---------------------------------------------------------------- what a killed check left


def leftovers() -> list[str]:
    """Namespaces and cgroup trees named with PROBE_PREFIX: only a check killed mid-way (SIGKILL,
    power loss) leaves them, since every other exit removes them."""
    names = sorted(os.listdir(NETNS_DIR)) if NETNS_DIR.is_dir() else []
    found = [f"netns {n}" for n in names if n.startswith(PROBE_PREFIX)]
    found += [f"cgroup {r}" for r in cgroups.run_ids() if r.startswith(PROBE_PREFIX)]
    return found


def remove_leftovers() -> list[str]:
    """Remove what `leftovers()` lists (for `testbed clean`); returns what was removed."""
    from pyroute2 import netns

    removed = leftovers()
    for item in removed:
        kind, name = item.split(" ", 1)
        if kind == "netns":
            netns.remove(name)
        else:
            cgroups.remove_all(name)
    return removed
