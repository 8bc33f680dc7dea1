"""Campaigns: thousands of runs across plant mismatch, timing and controller settings.

`hil-gateway campaign CAMPAIGN.toml --out DIR` expands a campaign file (the base run of
`simulate` or `sim`, a grid and random draws over its options and the plant scenario's keys,
pass criteria on the metrics) into points, runs each through the same entry as the command
line (:func:`gateway.cli.simulate_inputs` / :func:`gateway.cli.sim_inputs`, then
:func:`gateway.session.run`), on Dask (a local cluster by default) or in this process, and
keeps one table of results in DIR that a re-run completes.

Modules, one job each:

* :mod:`~gateway.campaign.model` — the campaign file: axes, distributions, criteria;
* :mod:`~gateway.campaign.options` — the commands' options a campaign may set;
* :mod:`~gateway.campaign.points` — the points: values, configuration, content hash,
  the command that reproduces one;
* :mod:`~gateway.campaign.metrics` — a run's summary → the table's metric columns;
* :mod:`~gateway.campaign.runpoint` — one point on a worker, with its time limit;
* :mod:`~gateway.campaign.table` — the results table (Parquet parts, compacted);
* :mod:`~gateway.campaign.engine` — where batches run: this process or Dask;
* :mod:`~gateway.campaign.runner` — the campaign: skip what is done, run the rest, record;
* :mod:`~gateway.campaign.progress`, :mod:`~gateway.campaign.summary`,
  :mod:`~gateway.campaign.figures`, :mod:`~gateway.campaign.htmlpage` — what the user
  looks at (the page: `hil-gateway report DIR`);
* :mod:`~gateway.campaign.command` — `hil-gateway campaign` and `campaign show`.

Dask (`distributed`) and Parquet (`pyarrow`) are the optional extra ``campaign``; only the
engine and the table import them, and only when a campaign runs.
"""
