"""One run of a batch, as a Ray task executes it: threads pinned, then a new, resumed or reused run folder.

Everything here runs in the task's own process (a Ray worker that serves one task and exits), so it may set
process-wide thread counts; it is equally callable in a plain process (tests, debugging).
"""
from __future__ import annotations

import os
import sys
import time
import traceback
from pathlib import Path

from ggfslam.config import Config, config_differences, config_from_dict, load_config
from ggfslam.errors import RunDirError
from ggfslam.rundir import CONFIG_FILE, METRICS_FILE, RUN_INFO_FILE, is_run_dir, read_json

# variables the thread pools read when their library is first imported; a task's process gets them at its start
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def thread_env(threads: int) -> dict[str, str]:
    """Environment pinning every thread pool (OpenMP, MKL, OpenBLAS, numba) of a task's process to ``threads``."""
    return {name: str(threads) for name in THREAD_VARIABLES}


def pin_threads(threads: int) -> dict[str, int]:
    """Pin torch, numba and OpenCV of this process to ``threads``; returns the counts now in force."""
    import cv2
    import numba
    import torch

    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    cv2.setNumThreads(threads)
    return {"torch": torch.get_num_threads(), "numba": numba.get_num_threads(),
            "omp_env": int(os.environ.get("OMP_NUM_THREADS", "0") or 0)}


def run_state(run_dir: Path, config: Config) -> tuple[str, str]:
    """What to do with a run's folder: ``new``, ``resume``, ``finished`` (reuse it) or ``conflict`` (leave it
    alone: it is not this run); with the reason."""
    if not run_dir.exists() or (run_dir.is_dir() and not any(run_dir.iterdir())):
        return "new", ""
    if not run_dir.is_dir() or not is_run_dir(run_dir):
        return "conflict", f"{run_dir}: holds something that is not a ggfslam run; move it away or change --out"
    if not (run_dir / CONFIG_FILE).is_file():
        return "conflict", f"{run_dir}: a run without its {CONFIG_FILE}; move it away to run it again"
    try:
        diff = config_differences(load_config(run_dir / CONFIG_FILE), config)
    except Exception as e:  # noqa: BLE001 - a damaged config.yaml is a folder this batch must not touch
        return "conflict", f"{run_dir}: its {CONFIG_FILE} cannot be read ({e}); move the folder away to run it again"
    info = read_json(run_dir / RUN_INFO_FILE)
    finished = info.get("status") == "finished" and (run_dir / METRICS_FILE).is_file()
    if diff:
        shown = ", ".join(diff[:5]) + (f" and {len(diff) - 5} more" if len(diff) > 5 else "")
        return "conflict", (f"{run_dir}: a run with another configuration is there ({shown} differ); move it away or "
                            "rename the variant")
    if finished:
        return "finished", "finished earlier"
    return "resume", f"resuming ({info.get('status', 'no run.json')}, from frame {info.get('resume_from_frame', 0)})"


def one_line(e: BaseException) -> str:
    """An error as one line: its type and the first line of its message."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def execute(payload: dict) -> dict:
    """Run one planned run (``payload``: key, run_dir, config (JSON dict), threads, cwd, command) and return its
    outcome:
    status ``finished`` or ``failed``, action ``ran``/``resumed``/``skipped``, metrics, error, traceback, threads,
    task_wall_s. An error in the run is an outcome, not an exception; Ctrl-C (a cancelled task) propagates."""
    t0 = time.perf_counter()
    out = {"key": payload["key"], "status": "failed", "action": None, "metrics": None, "error": None,
           "traceback": None, "threads": None, "host": os.uname().nodename, "pid": os.getpid()}
    try:
        threads = int(payload["threads"])
        out["threads"] = pin_threads(threads)
        if payload.get("command"):
            sys.argv = list(payload["command"])  # run.json records the command that asked for the run, not Ray's
        cwd = payload.get("cwd")
        if cwd and Path(cwd).is_dir():
            os.chdir(cwd)  # relative dataset paths in configs are read from where the batch was started
        config = config_from_dict(payload["config"], payload["key"])
        config.runtime.num_threads = threads
        config.runtime.progress = False
        run_dir = Path(payload["run_dir"])
        state, why = run_state(run_dir, config)
        if state == "conflict":
            raise RunDirError(why)
        if state == "finished":
            out.update(status="finished", action="skipped", metrics=read_json(run_dir / METRICS_FILE))
        else:
            from ggfslam import slam

            metrics = slam.run(config, run_dir, progress=False, resume=state == "resume")
            out.update(status="finished", action="resumed" if state == "resume" else "ran", metrics=metrics)
    except Exception as e:  # noqa: BLE001 - any error of a run is its row's, the batch goes on
        out.update(error=one_line(e), traceback=traceback.format_exc())
    out["task_wall_s"] = time.perf_counter() - t0
    return out


__all__ = ["THREAD_VARIABLES", "execute", "one_line", "pin_threads", "run_state", "thread_env"]
