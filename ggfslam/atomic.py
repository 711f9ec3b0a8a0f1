"""Atomic file output: every file ggfslam writes appears whole or not at all.

A writer gets a temporary path beside the target (same folder, so the final ``os.replace`` is a rename on one file
system, atomic on POSIX and Windows) whose name ends in the target's suffix (Open3D, OpenCV and numpy choose the
format from it). The rename happens only when the writer returns; on any error, Ctrl-C or a failed write the
temporary file is removed and the target keeps its previous content. A process killed outright (SIGKILL) can
leave a ``.*.tmp-PID.*`` file behind, never a half-written target.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write instead of ``path``; renamed onto it when the block completes."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise FileNotFoundError(f"{path}: the writer produced no file")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")

