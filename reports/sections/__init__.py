"""The report's sections, one module per topic: each holds the figures its topic puts into
summary.json beside the writer of its part of the report. In the report's order:

- `run`: the run's metadata and outcome, nodes that did not exit cleanly, the node
  processes, and the recording (last in the report);
- `accuracy`: errors per method against ground truth, against the paper, trajectories, and
  the headline;
- `learner`: the split-point learner, and the learned, fixed and oracle splits replayed;
- `timing`: latency per split, accuracy against latency, real-time deadlines, DNN gaps;
- `network`: link events, delivered rates and the link self-test;
- `radio`: the radio along the route and EdgeLoc around each handover;
- `core_path`: each vehicle's path to its edge, and GTP-U on N3;
- `apps`: apps, cross-traffic and EdgeLoc under load;
- `fmt`: what they share: rounding for summary.json, a figure as a table cell.

What they share is a shape, not a class. A summary is a pure function of the `RunData`
(`<topic>_summary(data)` and the like: no files, no plotting) whose result `summarize` puts
under its key of summary.json; each module's docstring documents its keys. A writer,
`<name>_section(...)`, takes the summary dict and what else it reads (the `RunData`, the
drawn plots) and returns a `reports.document.Section`, or None where the run has nothing
for it. `reports.build` calls both in the report's order.
"""
