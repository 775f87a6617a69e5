"""``iscd campaign``: many recordings or simulated points decoded as tasks on Dask
distributed, resumable, with a summary table and a report (docs/campaign.md).

- :mod:`.manifest` the manifest (TOML or CSV) -> task specs, checked (one-line errors)
- :mod:`.identity` a task's identity: content hashes of its inputs + its parameters + the
                   iscd version; the stamps that let a re-run skip unchanged inputs
- :mod:`.tasks`    one task on a worker: replay a recording (or render and replay a
                   simulated point) into its own JSONL, written under a temporary name
- :mod:`.rows`     a task's summary row from its records (and the truth, where there is one)
- :mod:`.runner`   the runner over Dask: a LocalCluster or an existing scheduler, progress,
                   Ctrl-C; also runs ``iscd eval``'s sweeps (:mod:`.evalplan`)
- :mod:`.summary`  summary.parquet, summary.csv and report.md (with plots when matplotlib is there)
- :mod:`.campaign` the whole run: plan, skip what is done, run the rest, write the summary

Layering: this package imports :mod:`iscd.eval`, :mod:`iscd.recording`, :mod:`iscd.decode`
and :mod:`iscd.core` (and the simulator for simulated points); nothing below imports it.
"""
