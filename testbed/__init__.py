"""edgeloc-testbed: scenario model, topology, orchestration and the `testbed` CLI.

Nouns: a Scenario says what to build; a Node is a network namespace that runs processes; a Link
joins two nodes (veth, or TUN ends plus a relay); a Net is a built topology with its run id and
state file, which is what `down` and `clean` undo.
"""

__version__ = "0.1.0"
