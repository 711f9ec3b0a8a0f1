"""A batch's results: one row per run from its metrics.json, mean and spread over seeds, CSV/JSON/table."""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np

from ggfslam.atomic import write_text_atomic

# (column, metrics.json section, key, header shown in the table, format)
METRIC_COLUMNS = (
    ("ate_rmse_cm", "trajectory", "ate_rmse_cm", "ATE cm", "{:.2f}"),
    ("rpe_trans_cm", "trajectory", "rpe_trans_rmse_cm", "RPE cm", "{:.2f}"),
    ("rpe_rot_deg", "trajectory", "rpe_rot_rmse_deg", "RPE deg", "{:.2f}"),
    ("psnr", "rendering", "psnr", "PSNR dB", "{:.2f}"),
    ("ssim", "rendering", "ssim", "SSIM", "{:.3f}"),
    ("depth_l1_cm", "rendering", "depth_l1_cm", "depth L1 cm", "{:.2f}"),
    ("tracking_fps", "tracking", "fps", "frames/s", "{:.1f}"),
    ("wall_s", "system", "wall_seconds", "wall s", "{:.0f}"),
    ("peak_rss_mb", "system", "peak_rss_mb", "peak MiB", "{:.0f}"),
)
NUMERIC = tuple(c[0] for c in METRIC_COLUMNS)
COLUMNS = ("sequence", "variant", "seed", "status", "action", "attempts", *NUMERIC[:6], "resolution", *NUMERIC[6:],
           "frames", "error", "run_dir")


def metric_columns(metrics: dict | None) -> dict:
    """The table's figures from a run's metrics.json (NaN where the run has none, e.g. no ground truth)."""
    metrics = metrics or {}
    row = {col: float(metrics.get(sec, {}).get(key, math.nan)) if _is_number(metrics.get(sec, {}).get(key))
           else math.nan for col, sec, key, _, _ in METRIC_COLUMNS}
    r = metrics.get("rendering", {})
    row["resolution"] = f"{r['width']}x{r['height']}" if "width" in r and "height" in r else "-"
    row["frames"] = metrics.get("sequence", {}).get("frames")
    return row


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def make_row(spec, status: str, action: str | None = None, metrics: dict | None = None, error: str | None = None,
             attempts: int = 0) -> dict:
    """One results row of a planned run (``spec``: a ``plan.RunSpec``)."""
    return {"sequence": spec.sequence, "variant": spec.variant, "seed": spec.seed, "status": status,
            "action": action, "attempts": attempts, **metric_columns(metrics), "error": error,
            "run_dir": str(spec.run_dir), "key": spec.key}


def summarize(rows: list[dict]) -> list[dict]:
    """Mean and spread (sample standard deviation) of each figure over the seeds of every (sequence, variant);
    failed runs are counted, not averaged."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["sequence"], r["variant"]), []).append(r)
    out = []
    for (seq, var), rs in groups.items():
        ok = [r for r in rs if r["status"] == "finished"]
        s = {"sequence": seq, "variant": var, "runs": len(rs), "finished": len(ok),
             "resolution": ok[0]["resolution"] if ok else "-"}
        for col in NUMERIC:
            v = np.array([r[col] for r in ok if not math.isnan(r[col])], dtype=np.float64)
            s[f"{col}_mean"] = float(v.mean()) if v.size else math.nan
            s[f"{col}_std"] = float(v.std(ddof=1)) if v.size > 1 else (0.0 if v.size else math.nan)
        out.append(s)
    return out


def _json_safe(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None  # strict JSON has no NaN
    return v


def write_results(out: Path, plan_name: str, rows: list[dict], extra: dict | None = None) -> None:
    """``out/results.csv`` (one line per run) and ``out/results.json`` (runs, summary over seeds, the plan)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None or (isinstance(r.get(k), float) and math.isnan(r[k])) else r[k])
                    for k in COLUMNS})
    write_text_atomic(out / "results.csv", buf.getvalue())
    doc = {"plan": plan_name, "rows": [{k: _json_safe(v) for k, v in r.items()} for r in rows],
           "summary": [{k: _json_safe(v) for k, v in s.items()} for s in summarize(rows)], **(extra or {})}
    write_text_atomic(out / "results.json", json.dumps(doc, indent=1, allow_nan=False) + "\n")


def format_cell(v: float, fmt: str) -> str:
    """A figure formatted with ``fmt``; "-" where it is missing (None or NaN)."""
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


def format_spread(summary: dict, col: str, fmt: str) -> str:
    """``mean ± spread`` of column ``col`` in a ``summarize`` line; "-" where none of its runs finished."""
    if not summary["finished"]:
        return "-"
    return f"{format_cell(summary[f'{col}_mean'], fmt)} ± {format_cell(summary[f'{col}_std'], fmt)}"


def results_table(rows: list[dict], title: str = "batch"):
    """A rich Table of the runs; with repeated seeds, one line per (sequence, variant) with mean ± spread."""
    from rich.table import Table

    repeated = any(r["seed"] is not None for r in rows)
    heads = [c[3] for c in METRIC_COLUMNS]
    table = Table("sequence", "variant", "runs" if repeated else "status", *heads[:6], "at", *heads[6:],
                  title=title)
    if repeated:
        for s in summarize(rows):
            cells = [format_spread(s, c, fmt) for c, _, _, _, fmt in METRIC_COLUMNS]
            table.add_row(s["sequence"], s["variant"], f"{s['finished']}/{s['runs']}", *cells[:6], s["resolution"],
                          *cells[6:])
        return table
    for r in rows:
        cells = [format_cell(r[c], fmt) for c, _, _, _, fmt in METRIC_COLUMNS]
        status = r["status"] if r["status"] == "finished" else f"[red]{r['status']}[/red]"
        table.add_row(r["sequence"], r["variant"], status, *cells[:6], r["resolution"], *cells[6:])
    return table


def run_line(row: dict) -> str:
    """The progress line printed when a run ends."""
    if row["status"] != "finished":
        return f"{row['key']}: {row['status']}: {row['error']}"
    parts = [f"ATE {format_cell(row['ate_rmse_cm'], '{:.2f}')} cm",
             f"PSNR {format_cell(row['psnr'], '{:.2f}')} dB at {row['resolution']}",
             f"{format_cell(row['tracking_fps'], '{:.1f}')} frames/s",
             f"wall {format_cell(row['wall_s'], '{:.0f}')} s"]
    what = {"skipped": "finished earlier", "resumed": "resumed, finished"}.get(row["action"], "finished")
    return f"{row['key']}: {what}: " + ", ".join(parts)


__all__ = ["COLUMNS", "METRIC_COLUMNS", "format_cell", "format_spread", "make_row", "metric_columns", "results_table",
           "run_line", "summarize", "write_results"]
