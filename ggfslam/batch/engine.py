"""Ray as the batch's engine: start or join an instance, run each planned run as one task, report how it ended.

Each task runs in a fresh worker process (``max_calls=1``): a run's memory is returned to the system when it
ends, and the process starts with its thread pools pinned (``task.thread_env``), since OpenMP and numba read
their thread counts once, at import.
"""
from __future__ import annotations

import logging
import os
from typing import Any

from ggfslam.batch.task import execute, one_line, thread_env
from ggfslam.errors import BatchError

OBJECT_STORE_BYTES = 100 * 1024**2  # tasks exchange small dicts; Ray's default would reserve 30% of the RAM
# environment a task takes from the batch's (paths every node reads the same way)
FORWARDED_VARIABLES = ("GGFSLAM_DATA",)


class RayEngine:
    """Runs ``task.execute`` payloads as Ray tasks on a local instance (``local``) or a cluster (``auto`` or
    ``HOST:PORT``)."""

    def __init__(self, address: str = "local", cpus: int | None = None):
        try:
            import ray
        except ImportError:
            raise BatchError("Ray is not installed; run scripts/install.sh (or pip install 'ray>=2.40')") from None
        self.ray = ray
        self.address = address
        kwargs: dict[str, Any] = {"log_to_driver": False, "configure_logging": True, "logging_level": logging.ERROR}
        try:
            if address == "local":
                if cpus is not None and cpus < 1:
                    raise BatchError(f"--cpus {cpus}: expected at least 1")
                ray.init(num_cpus=cpus, include_dashboard=False, object_store_memory=OBJECT_STORE_BYTES, **kwargs)
            else:
                if cpus is not None:
                    raise BatchError("--cpus sets the size of a local Ray instance; a cluster has its own")
                ray.init(address=address, **kwargs)
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise BatchError(f"--ray {address}: cannot start or join Ray ({one_line(e)})") from None
        self._remote = ray.remote(max_calls=1)(execute)

    def total_cpus(self) -> float:
        """CPUs of the Ray instance (all nodes)."""
        return float(self.ray.cluster_resources().get("CPU", 0.0))

    def largest_node_cpus(self) -> float:
        """CPUs of the largest node (a task must fit on one)."""
        return max((float(n["Resources"].get("CPU", 0.0)) for n in self.ray.nodes() if n.get("Alive")), default=0.0)

    def submit(self, payload: dict, num_cpus: float, memory_gb: float | None, threads: int):
        """Start one run as a task; returns its reference."""
        env = thread_env(threads)
        env.update({k: os.environ[k] for k in FORWARDED_VARIABLES if k in os.environ})
        options: dict[str, Any] = {"num_cpus": num_cpus, "max_retries": 0, "runtime_env": {"env_vars": env}}
        if memory_gb is not None:
            options["memory"] = int(memory_gb * 1024**3)
        return self._remote.options(**options).remote(payload)

    def wait(self, refs: list, timeout: float) -> list:
        """The references among ``refs`` whose tasks have ended (waiting at most ``timeout`` seconds)."""
        if not refs:
            return []
        ready, _ = self.ray.wait(refs, num_returns=len(refs), timeout=timeout)
        return ready

    def outcome(self, ref, key: str) -> dict:
        """How a task ended: its ``execute`` outcome, or a failed / interrupted one when its process died or it was
        cancelled."""
        exc = self.ray.exceptions
        try:
            return self.ray.get(ref)
        except exc.TaskCancelledError:
            return {"key": key, "status": "interrupted", "error": "interrupted (Ctrl-C)"}
        except exc.OutOfMemoryError:
            error = ("killed by Ray's memory monitor (the node ran short of memory); set memory_gb in the plan so "
                     "fewer runs share a node")
        except exc.WorkerCrashedError:
            error = "killed: the process running it died (a crash or a kill signal)"
        except exc.RayTaskError as e:  # execute() turns errors into outcomes; this is an interrupt inside it
            cause = getattr(e, "cause", None)
            if isinstance(cause, KeyboardInterrupt):
                return {"key": key, "status": "interrupted", "error": "interrupted (Ctrl-C)"}
            error = one_line(cause if cause is not None else e)
        except exc.RayError as e:
            error = one_line(e)
        return {"key": key, "status": "failed", "error": error}

    def cancel(self, refs: list, force: bool) -> None:
        """Cancel tasks: without ``force`` a KeyboardInterrupt in each (the run saves its checkpoint), with it a
        kill."""
        for ref in refs:
            try:
                self.ray.cancel(ref, force=force)
            except Exception:  # noqa: BLE001 - a task that ended meanwhile cannot be cancelled
                pass

    def close(self) -> None:
        """Leave the Ray instance (a local one stops)."""
        self.ray.shutdown()


__all__ = ["RayEngine"]
