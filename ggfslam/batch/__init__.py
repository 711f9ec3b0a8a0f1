"""Batches of runs (``ggfslam batch``): a plan of sequences x variants x seeds, each run an ordinary run folder,
executed as Ray tasks on this machine or a cluster, the results gathered into one table.

- ``plan``: the plan file, validated and expanded into runs.
- ``task``: one run inside its task (threads pinned; new, resumed or reused).
- ``engine``: Ray (start or join an instance, submit, wait, cancel).
- ``runner``: the batch itself (sorting, retries, Ctrl-C, progress).
- ``results``: rows, mean and spread over seeds, results.csv / results.json / the printed table.
"""
from ggfslam.batch.plan import Plan, RunSpec, build_plan, load_plan
from ggfslam.batch.results import results_table, summarize
from ggfslam.batch.runner import run_batch

__all__ = ["Plan", "RunSpec", "build_plan", "load_plan", "results_table", "run_batch", "summarize"]
