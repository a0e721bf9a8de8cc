"""`testbed sweep`: one scenario, a grid of variants, one comparison report across them.

A variant is the scenario file with some fields replaced (`--set KEY=V1,V2,...`, one axis per
option; the grid is every combination). Overrides are made on the YAML tree, before any checking,
and each variant is then checked by the scenario loader itself: a value is valid in a sweep
exactly when it would be valid written in the file, and a wrong one is reported the way
`testbed validate` reports it (field path, expected, found), naming the `--set` that made it.

Keys are dotted paths into the YAML, as an author reads it:

- mapping keys: `workload.learner.window`, `links.air.uplink.delay`, `duration`, `seed`;
- list items by index or by name: `timeline[1].uplink`, `topology.vehicles[0].cpu`,
  `topology.vehicles.av2.cpu` (an item whose `name`, `gnb` or `link` is that word);
- one link alone: `links.av1-gnb1.uplink.delay` becomes (or changes) that link's entry in
  `links.overrides`, so the other links keep the `links.air` / `links.backhaul` defaults.

Values are YAML scalars as in the file (`8ms`, `20mbit`, `0.5%`, `30`, `true`, `null`) or a flow
list in brackets (`[image,conv3]`: commas inside brackets do not separate values).

Each variant runs with the offline replay (`testbed replay`'s engine, every vehicle of the
scenario, DNN outputs shared between variants that drive the same frames) or, with `real=True`,
as a real run (`testbed run`: namespaces, links, ROS 2 nodes). The report is `sweep.json`,
`sweep.md` (one table) and `sweep.png` (errors and latency across the variants).

The package: `grid` (axes, `--set` parsing, overrides on the YAML tree, `shorten`,
`rescale`), `jobs` (one run of a variant with one seed: the replay engine, the real-run rows),
`engines` (`run_sweep`: the jobs one by one here), `rayengine` (the jobs as Ray tasks on a
cluster, `--engine ray`), `stats` (`--seeds`: derived seeds, mean and 95% interval), `output`
(the rows, the report and its three files).

`--seeds N` runs each variant N times, with the scenario's seed and the N-1 after it (every
random choice of a run follows its seed: the synthetic drive, loss and jitter draws). sweep.md
then adds a table of each figure's mean +- 95% confidence interval (Student's t over the N
rows), sweep.json its `statistics` (mean, half width, n and the values per metric), and
sweep.png error bars.
"""

from testbed.sweep.engines import run_sweep
from testbed.sweep.grid import (
    MAX_VARIANTS,
    Axis,
    grid,
    label,
    load_tree,
    parse_set,
    parse_value,
    path_segments,
    read_tree,
    rescale,
    set_path,
    shorten,
    split_values,
    variant_tree,
)
from testbed.sweep.jobs import METHODS, Progress
from testbed.sweep.output import SweepReport, VariantResult, markdown, plot, write_report

__all__ = [
    "MAX_VARIANTS",
    "METHODS",
    "Axis",
    "Progress",
    "SweepReport",
    "VariantResult",
    "grid",
    "label",
    "load_tree",
    "markdown",
    "parse_set",
    "parse_value",
    "path_segments",
    "plot",
    "read_tree",
    "rescale",
    "run_sweep",
    "set_path",
    "shorten",
    "split_values",
    "variant_tree",
    "write_report",
]
