"""Reports: read a run's MCAP, compute metrics, draw plots, write html/md/json.

`reports.build.build_report(run_folder)` is the entry point (`testbed report`, and the end of
`testbed run`). Modules: `mcapread` (run.mcap -> `RunData`, tolerant of cut files),
`summary` (every figure, summary.json and its documented keys), `plots` (matplotlib
figures), `document` (the report as sections, and Markdown), `html` (self-contained HTML).
"""
