"""Reports: read a run's MCAP, compute metrics, draw plots, write html/md/json.

`reports.build.build_report(run_folder)` is the entry point (`testbed report`, and the end of
`testbed run`). Modules: `mcapread` (run.mcap -> `RunData`, tolerant of cut files), `build`
(the pipeline: summary.json and the report files), `sections` (one module per part of the
report: its figures for summary.json, their documented keys, and its writer), `plots`
(matplotlib figures), `document` (the report as sections, and Markdown), `html`
(self-contained HTML).

What report.html shows: per method (VO, DNN, Kalman, EdgeLoc) total / mean / median / RMSE / p95
/ max position and heading error; the paper's four totals and three reductions beside ours;
latency per split; the split chosen over time with the uplink cap, delivered rate, detector
resets and outages, and per network phase the split played most against the fastest in
hindsight; accuracy against latency; error over time and box plots; trajectories; real-time
deadline misses; gaps in DNN answers (EdgeLoc on VO alone); link events, traffic, the link
self-test table and the backend that ran; nodes, and for a failed node its last log lines.
Anything not recorded is named as such. The same MCAP gives a byte-identical summary.json and
report.md anywhere, since run.json (paths to the edge, apps, cross-traffic and its load windows)
is attached to it; a run that ended before writing run.json has a report that names what it
leaves out. `report: {compare: false}` leaves the fixed-split replays out of a run's report and
`testbed report RUN --compare` adds them later. `make report-screenshot` renders a report in
headless Chromium and saves report-screenshot.png; the tests check that every figure loads.
"""
