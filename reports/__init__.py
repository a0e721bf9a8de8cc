"""Reports: read a run's MCAP, compute metrics, draw plots, write html/md/json."""
