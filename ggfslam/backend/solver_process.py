"""Bundle adjustments (and loop closures' pose graphs) solved in a child process, so that tracking runs while
GTSAM optimizes.

GTSAM's Python bindings hold the GIL for the whole of an optimization: a backend thread that optimizes stalls the
tracking thread beside it (benchmarks/bench_backend_gil.py: a Python loop took 1.50 s alone, 8.53 s beside a BA
thread, 1.22 s beside a BA process). The backend thread therefore only reads the problem from the map
(``local_ba.ba_problem``, plain arrays), sends it here and writes the answer back (``local_ba.apply_solution``);
the map itself never leaves the tracking process.

The child is ``python -m ggfslam.backend.solver_process``, started with ``subprocess`` (not ``multiprocessing``:
a script that calls ``slam.run`` needs no ``if __name__ == "__main__"`` guard). Messages are length-prefixed
pickles on its stdin and stdout; everything else the child prints goes to stderr.
"""
from __future__ import annotations

import logging
import pickle
import struct
import subprocess
import sys
import threading
import traceback

log = logging.getLogger("ggfslam.backend")
_HEADER = struct.Struct("<Q")


def _send(stream, obj) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_HEADER.pack(len(data)) + data)
    stream.flush()


def _receive(stream):
    """The next message, or raises EOFError when the other side has gone."""
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        raise EOFError
    size = _HEADER.unpack(head)[0]
    data = stream.read(size)
    if len(data) < size:
        raise EOFError
    return pickle.loads(data)


class SolverError(RuntimeError):
    """The child process failed to solve a problem (its traceback is the message)."""


class SolverProcess:
    """A child process that solves ``local_ba.BAProblem``s (``solve``) and pose graphs (``pose_graph``); a call
    blocks the calling thread without the GIL.

    If the child dies (killed, out of memory), the problem in flight and every later one are solved in this process,
    after one warning: the run goes on, as it would without a solver process."""

    def __init__(self):
        self._lock = threading.Lock()  # one problem in flight
        self._proc: subprocess.Popen | None = subprocess.Popen(
            [sys.executable, "-m", "ggfslam.backend.solver_process"], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self.solved = 0  # problems the child solved
        self.fallback: str = ""  # why problems are solved in this process ("": they are not)

    @property
    def alive(self) -> bool:
        """Whether problems still go to the child."""
        return self._proc is not None and self._proc.poll() is None

    def solve(self, problem):
        """The ``BASolution`` of a ``BAProblem``, from the child (or in this process once the child is gone)."""
        return self._call("bundle_adjustment", problem)

    def pose_graph(self, poses: dict, edges: list, fixed_ids: set, robust: bool) -> dict:
        """``pose_graph.optimize_pose_graph``'s poses, from the child (or in this process once it is gone)."""
        return self._call("pose_graph", poses, edges, fixed_ids, robust)

    def _call(self, name: str, *args):
        with self._lock:
            if self._proc is not None:
                try:
                    _send(self._proc.stdin, (name, args))
                    status, payload = _receive(self._proc.stdout)
                except (EOFError, BrokenPipeError, OSError) as e:
                    self._lost(e)
                else:
                    if status == "error":
                        raise SolverError(f"{name.replace('_', ' ')} failed in the solver process:\n{payload}")
                    self.solved += 1
                    return payload
        return _FUNCTIONS[name]()(*args)

    def _lost(self, error: BaseException) -> None:
        code = self._proc.wait(timeout=5) if self._proc.poll() is None else self._proc.returncode
        self.fallback = f"the solver process ended (exit code {code}, {type(error).__name__})"
        log.warning("%s: bundle adjustments are solved in the tracking process from now on", self.fallback)
        self._close_pipes()
        self._proc = None

    def _close_pipes(self) -> None:
        for stream in (self._proc.stdin, self._proc.stdout):
            try:
                stream.close()
            except OSError:
                pass

    def close(self) -> None:
        """Stop the child (it exits when its input closes)."""
        with self._lock:
            if self._proc is None:
                return
            self._close_pipes()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            self._proc = None

    def __del__(self):
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.poll() is None:
            proc.kill()


def _solve_ba():
    from ggfslam.backend.local_ba import solve

    return solve


def _solve_pose_graph():
    from ggfslam.backend.pose_graph import optimize_pose_graph

    return optimize_pose_graph


_FUNCTIONS = {"bundle_adjustment": _solve_ba, "pose_graph": _solve_pose_graph}  # name -> (import on first use)


def _serve() -> None:
    """The child's loop: (name, args) in, ("ok", result) or ("error", traceback) out, until stdin closes."""
    import os
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the run's to handle: it closes our input when done
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # a stray print must not corrupt the message stream
    inp = sys.stdin.buffer
    while True:
        try:
            name, args = _receive(inp)
        except EOFError:
            return
        try:
            reply = ("ok", _FUNCTIONS[name]()(*args))
        except Exception:  # noqa: BLE001 - the parent raises it with the child's traceback
            reply = ("error", traceback.format_exc())
        _send(out, reply)


if __name__ == "__main__":
    _serve()
