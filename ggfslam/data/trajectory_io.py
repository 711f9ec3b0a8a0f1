"""Trajectory files in TUM format: ``timestamp tx ty tz qx qy qz qw`` per line, camera-to-world."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ggfslam.atomic import write_text_atomic
from ggfslam.errors import DatasetError
from ggfslam.geometry.se3 import pose_from_tum, pose_to_tum, rigidity_error


def parse_numeric_lines(path: str | Path, min_cols: int) -> list[tuple[int, list[str]]]:
    """Data lines of a whitespace table as (line number, fields); skips blank, ``#`` and non-numeric header lines."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found")
    rows = []
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"cannot read text file ({e})") from None
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.replace(",", " ").split()
        if not fields:  # only separators: as good as blank
            continue
        try:
            float(fields[0])
        except ValueError:
            # TUM headers sometimes lack the '#' (fr1/xyz): a header line never starts with a number
            if not rows:
                continue
            raise DatasetError(path, f"expected a timestamp in the first column, got {fields[0]!r}", lineno) from None
        if len(fields) < min_cols:
            raise DatasetError(path, f"expected at least {min_cols} columns, got {len(fields)}", lineno)
        rows.append((lineno, fields))
    return rows


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: timestamps [N] and camera-to-world poses [N, 4, 4], checked finite and rigid."""
    stamps, poses = [], []
    for lineno, fields in parse_numeric_lines(path, 8):
        try:
            vals = np.array([float(x) for x in fields[:8]])
        except ValueError:
            raise DatasetError(path, f"expected 8 numbers 'timestamp tx ty tz qx qy qz qw', got {fields[:8]}", lineno) from None
        if not np.all(np.isfinite(vals)):
            raise DatasetError(path, "pose has non-finite values", lineno)
        qn = np.linalg.norm(vals[4:8])
        if abs(qn - 1.0) > 1e-2:
            raise DatasetError(path, f"quaternion is not unit length (|q| = {qn:.4g})", lineno)
        stamps.append(vals[0])
        poses.append(pose_from_tum(vals[1:8]))
    if not stamps:
        raise DatasetError(path, "trajectory file holds no poses")
    stamps = np.array(stamps)
    if np.any(np.diff(stamps) < 0):
        order = np.argsort(stamps, kind="stable")
        stamps, poses = stamps[order], [poses[i] for i in order]
    return stamps, np.stack(poses)


def write_tum_trajectory(path: str | Path, stamps: np.ndarray, poses: np.ndarray, header: str | None = None) -> None:
    """Write timestamps [N] and camera-to-world poses [N, 4, 4] as a TUM trajectory file."""
    lines = []
    if header:
        lines += [f"# {h}" for h in header.splitlines()]
    lines.append("# timestamp tx ty tz qx qy qz qw")
    for t, T in zip(stamps, poses):
        err = rigidity_error(T)
        if err:
            raise ValueError(f"refusing to write pose at t={t}: {err}")
        v = pose_to_tum(T)
        lines.append(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in v))
    write_text_atomic(path, "\n".join(lines) + "\n")
