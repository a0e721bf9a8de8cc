"""Reports: read a run's MCAP, compute metrics, draw plots, write html/md/json.

`reports.build.build_report(run_folder)` is the entry point (`testbed report`, and the end of
`testbed run`). Modules: `mcapread` (run.mcap -> `RunData`, tolerant of cut files), `build`
(the pipeline: summary.json and the report files), `sections` (one module per part of the
report: its figures for summary.json, their documented keys, and its writer), `plots`
(matplotlib figures), `document` (the report as sections, and Markdown), `html`
(self-contained HTML).
"""
