"""``ggfslam batch``: every run of a plan on the engine, progress as runs end, results gathered into one table.

Stages: take the batch folder (one batch at a time), sort the runs (a broken configuration or a folder that is not
this run: failed at once; finished earlier: reused), run the rest on Ray with retries, and write results.csv and
results.json after every run that ends, so an interrupted batch keeps the table of what it finished.
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console

from ggfslam.atomic import write_text_atomic
from ggfslam.batch.plan import Plan, RunSpec
from ggfslam.batch.results import make_row, run_line, write_results
from ggfslam.batch.task import run_state
from ggfslam.errors import BatchError, GGFSlamError
from ggfslam.rundir import METRICS_FILE, read_json

LOCK_FILE = ".batch.lock"
PLAN_FILE = "plan.json"  # the plan as resolved by the last invocation
ERRORS_DIR = "errors"  # full tracebacks of failed runs, one file per run
CANCEL_GRACE_S = 60.0  # a cancelled run's time to save its checkpoint before it is killed


@dataclass
class _Progress:
    """Counts for the overall line: done (finished or reused), failed, running, and the ETA from this batch's
    pace."""

    total: int
    started: float = field(default_factory=time.perf_counter)
    done: int = 0
    failed: int = 0
    running: int = 0
    completed_here: int = 0  # runs that ran (or failed) in this invocation: the pace
    left_to_run: int = 0

    def describe(self) -> str:
        eta = "-"
        if self.completed_here and self.left_to_run:
            pace = (time.perf_counter() - self.started) / self.completed_here
            eta = _duration(pace * self.left_to_run)
        return f"{self.done} done, {self.running} running, {self.failed} failed, ETA {eta}"


def _duration(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def _payload(spec: RunSpec) -> dict:
    assert spec.config is not None
    return {"key": spec.key, "run_dir": str(spec.run_dir), "config": spec.config.model_dump(mode="json"),
            "threads": spec.threads, "cwd": os.getcwd(), "command": [*sys.argv, f"[{spec.key}]"]}


def _save_traceback(out: Path, row: dict, text: str | None) -> None:
    if not text:
        return
    path = out / ERRORS_DIR / (row["key"].replace("/", "__") + ".txt")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, text)
    row["traceback_file"] = str(path)


class _Batch:
    """One invocation of a plan: its rows (in plan order), the progress display and the results files."""

    def __init__(self, plan: Plan, out: Path, console: Console):
        self.plan, self.out, self.console = plan, out, console
        self.rows: dict[str, dict] = {r.key: make_row(r, "pending") for r in plan.runs}
        self.progress = _Progress(len(plan.runs))
        self._bar = None
        self._task = None

    def record(self, spec: RunSpec, row: dict, save: bool = True) -> None:
        """A run has ended (or was sorted out): its row, its line, the counts, the files (with ``save``)."""
        self.rows[spec.key] = row
        p = self.progress
        if row["status"] == "finished":
            p.done += 1
        else:
            p.failed += 1
        index = p.done + p.failed
        line = f"[{index}/{p.total}] {run_line(row)}"
        self.console.print(line, highlight=False, markup=False, soft_wrap=True)
        if save:
            self.save()
        self.refresh()

    def save(self) -> None:
        write_results(self.out, self.plan.name, list(self.rows.values()), {"source": self.plan.source})

    def refresh(self) -> None:
        if self._bar is not None:
            p = self.progress
            self._bar.update(self._task, completed=p.done + p.failed, description=p.describe())

    def __enter__(self):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        # the bar lives on a terminal only; a log gets the per-run lines
        self._bar = Progress(TextColumn("batch"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                             TextColumn("{task.description}"), console=self.console, transient=False,
                             disable=not self.console.is_terminal)
        self._bar.__enter__()
        self._task = self._bar.add_task(self.progress.describe(), total=self.progress.total)
        return self

    def __exit__(self, *exc):
        self.refresh()
        self._bar.__exit__(*exc)


def _sort_runs(batch: _Batch) -> list[RunSpec]:
    """Rows for runs that need no task (broken configuration, someone else's folder, finished earlier); returns
    the runs to execute."""
    todo = []
    for spec in batch.plan.runs:
        if spec.error is not None:
            batch.record(spec, make_row(spec, "failed", error=spec.error), save=False)
            continue
        state, why = run_state(spec.run_dir, spec.config)
        if state == "finished":
            try:
                row = make_row(spec, "finished", "skipped", read_json(spec.run_dir / METRICS_FILE))
            except GGFSlamError as e:  # a damaged metrics.json: the folder is left as it is
                row = make_row(spec, "failed", error=f"{e}; move the run away to run it again")
            batch.record(spec, row, save=False)
        elif state == "conflict":
            batch.record(spec, make_row(spec, "failed", error=why), save=False)
        else:
            todo.append(spec)
    batch.save()
    return todo


def _check_fits(engine, plan: Plan) -> None:
    need = max((r.num_cpus for r in plan.runs), default=0)
    have = engine.largest_node_cpus()
    if need > have:
        raise BatchError(f"{plan.source}: num_cpus {need:g} per run, but the largest Ray node has {have:g} CPUs")


def _execute(batch: _Batch, todo: list[RunSpec], engine, retries: int) -> None:
    """Run ``todo`` on the engine, as many at a time as its CPUs allow; a failed run is tried again up to
    ``retries`` times (resuming from its checkpoint)."""
    queue = list(todo)
    attempts: dict[str, int] = {}
    running: dict = {}  # ref -> spec
    batch.progress.left_to_run = len(queue)
    try:
        while queue or running:
            slots = max(1, int(engine.total_cpus() // max(r.num_cpus for r in todo)))
            while queue and len(running) < slots:
                spec = queue.pop(0)
                attempts[spec.key] = attempts.get(spec.key, 0) + 1
                running[engine.submit(_payload(spec), spec.num_cpus, spec.memory_gb, spec.threads)] = spec
            batch.progress.running = len(running)
            batch.refresh()
            for ref in engine.wait(list(running), timeout=0.5):
                spec = running.pop(ref)
                row = _outcome_row(batch.out, spec, engine.outcome(ref, spec.key), attempts[spec.key])
                if row["status"] == "failed" and attempts[spec.key] <= retries:
                    batch.console.print(f"{spec.key}: failed (attempt {attempts[spec.key]} of {retries + 1}): "
                                        f"{row['error']}; trying again", highlight=False, markup=False)
                    queue.append(spec)
                    continue
                batch.progress.completed_here += 1
                batch.progress.left_to_run -= 1
                batch.progress.running = len(running)
                batch.record(spec, row)
    except KeyboardInterrupt:
        _stop(batch, engine, running, attempts)
        raise


def _outcome_row(out: Path, spec: RunSpec, outcome: dict, attempts: int) -> dict:
    """The row of a task that ended (its traceback saved under ``out``)."""
    row = make_row(spec, outcome["status"], outcome.get("action"), outcome.get("metrics"), outcome.get("error"),
                   attempts)
    row["threads"] = outcome.get("threads")
    _save_traceback(out, row, outcome.get("traceback"))
    return row


def _stop(batch: _Batch, engine, running: dict, attempts: dict[str, int]) -> None:
    """Ctrl-C: running runs are interrupted (each saves a checkpoint a later invocation resumes from), killed if
    they take longer than ``CANCEL_GRACE_S``; finished runs stay as they are."""
    batch.console.print(f"stopping: {len(running)} running run(s) save a checkpoint (Ctrl-C again to kill them)",
                        highlight=False, markup=False)
    engine.cancel(list(running), force=False)
    deadline = time.perf_counter() + CANCEL_GRACE_S
    try:
        while running and time.perf_counter() < deadline:
            for ref in engine.wait(list(running), timeout=0.5):
                spec = running.pop(ref)
                row = _outcome_row(batch.out, spec, engine.outcome(ref, spec.key), attempts[spec.key])
                if row["status"] != "finished":
                    row.update(status="interrupted", error=row["error"] or "interrupted (Ctrl-C)")
                batch.record(spec, row)
    except KeyboardInterrupt:
        pass
    engine.cancel(list(running), force=True)
    for spec in running.values():
        batch.record(spec, make_row(spec, "interrupted", error="killed at Ctrl-C before it saved a checkpoint",
                                    attempts=attempts[spec.key]))
    running.clear()


def run_batch(plan: Plan, out: str | Path, ray: str = "local", retries: int = 0, cpus: int | None = None,
              console: Console | None = None) -> list[dict]:
    """Run every run of ``plan`` under ``out`` (see the module docstring); returns the rows in plan order."""
    from filelock import FileLock, Timeout

    console = console or Console()
    out = Path(out)
    if retries < 0:
        raise BatchError(f"--retries {retries}: expected 0 or more")
    if out.is_dir() and not (out / PLAN_FILE).is_file() and any(p.name != LOCK_FILE for p in out.iterdir()):
        # neither a batch folder nor one holding this plan's runs (an earlier `ggfslam bench`): the user's files
        if not any((out / r.key.split("/")[0]).is_dir() for r in plan.runs):
            raise BatchError(f"{out}: not a batch folder (no {PLAN_FILE}) and not empty; choose another --out")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BatchError(f"{out}: cannot create the batch folder ({e.strerror})") from None
    lock = FileLock(str(out / LOCK_FILE))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise BatchError(f"{out}: another ggfslam batch is running in this folder") from None
    try:
        write_text_atomic(out / PLAN_FILE, json.dumps(plan.spec, indent=1) + "\n")
        batch = _Batch(plan, out, console)
        try:
            with batch:
                todo = _sort_runs(batch)
                if todo:
                    from ggfslam.batch.engine import RayEngine

                    engine = RayEngine(ray, cpus)
                    try:
                        _check_fits(engine, plan)
                        _execute(batch, todo, engine, retries)
                    finally:
                        engine.close()
        except KeyboardInterrupt:
            for row in batch.rows.values():
                if row["status"] == "pending":
                    row["status"] = "not run"
            batch.save()
            raise
        batch.save()
        return list(batch.rows.values())
    finally:
        lock.release()


__all__ = ["run_batch", "LOCK_FILE", "ERRORS_DIR"]
