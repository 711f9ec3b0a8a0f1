"""Where the shared real data lives, and small file helpers shared by the dataset readers."""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ggfslam.errors import DatasetError

DATA_ENV_VAR = "GGFSLAM_DATA"


def default_data_root() -> Path:
    """Folder of the shared real data: ``$GGFSLAM_DATA``, else ``shared/data`` next to the repository."""
    env = os.environ.get(DATA_ENV_VAR)
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[2]  # ggfslam/data/paths.py -> repository root
    return repo.parent / "shared" / "data"


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers by value ("img2" before "img10")."""
    # re.split with a capture group alternates text, number, text, ... so positions always compare like types
    return tuple(int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", name))


def require_dir(path: Path, what: str) -> Path:
    """Return ``path`` if it is a folder, else raise DatasetError saying which folder was expected."""
    if not path.is_dir():
        raise DatasetError(path, f"{what} folder not found")
    return path


def list_files(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    """Non-hidden files in ``folder`` with one of ``suffixes`` (case-insensitive), in natural order."""
    files = [p for p in folder.iterdir()
             if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in suffixes]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_number_rows(path: str | Path, ncols: int) -> list[tuple[int, np.ndarray]]:
    """Rows of exactly ``ncols`` numbers as (line number, values [ncols]); skips blank and ``#`` lines."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read text file ({e})") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.replace(",", " ").split()
        if len(fields) != ncols:
            raise DatasetError(path, f"expected {ncols} numbers, got {len(fields)} fields", lineno)
        try:
            values = np.array([float(x) for x in fields])  # [ncols]; float() also accepts inf/nan
        except ValueError:
            raise DatasetError(path, f"expected {ncols} numbers, got {s[:80]!r}", lineno) from None
        rows.append((lineno, values))
    return rows


def read_matrix(path: str | Path, rows: int, cols: int) -> np.ndarray:
    """A ``rows`` x ``cols`` matrix written one row per line (ScanNet pose and intrinsic files)."""
    data = read_number_rows(path, cols)
    if len(data) != rows:
        raise DatasetError(path, f"expected a {rows}x{cols} matrix ({rows} lines of {cols} numbers), "
                                 f"got {len(data)} lines")
    return np.stack([values for _, values in data])  # [rows, cols]
