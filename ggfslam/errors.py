"""Error types that carry a user-facing, one-line message (the CLI prints them without a traceback)."""
from __future__ import annotations

from pathlib import Path


class GGFSlamError(Exception):
    """Base class for every error caused by user input (files, configuration, command line)."""


class DatasetError(GGFSlamError):
    """A dataset file is missing, unreadable or holds something other than what was expected."""

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path = str(path)
        self.line = line
        self.reason = message
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")

    def __reduce__(self):
        # pickled by its own arguments, so it survives a worker process (benchmarks, batch runs) intact
        return type(self), (self.path, self.reason, self.line)


class ConfigError(GGFSlamError):
    """A configuration file or override is invalid."""


class RunDirError(GGFSlamError):
    """A run directory cannot be created, read or would be overwritten."""


class ViewerError(GGFSlamError):
    """The web viewer cannot start (port taken, address not available, viser not installed)."""


class BatchError(GGFSlamError):
    """A batch cannot start (Ray missing or unreachable, a plan asking more than the cluster has, a busy folder)."""
