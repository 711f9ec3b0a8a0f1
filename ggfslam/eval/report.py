"""Metric tables for the terminal (rich) and the JSON layout of ``metrics.json``."""
from __future__ import annotations

import math

from rich.console import Console
from rich.table import Table
from rich.text import Text

# (section, key, label, format); "{res}" in a label is the resolution the figure was measured at
ROWS = [
    ("trajectory", "ate_rmse_cm", "ATE RMSE [cm] (all frames)", "{:.2f}"),
    ("trajectory", "ate_mean_cm", "ATE mean [cm]", "{:.2f}"),
    ("trajectory", "ate_max_cm", "ATE max [cm]", "{:.2f}"),
    ("trajectory", "rpe_trans_rmse_cm", "RPE trans RMSE [cm/frame]", "{:.2f}"),
    ("trajectory", "rpe_rot_rmse_deg", "RPE rot RMSE [deg/frame]", "{:.3f}"),
    ("trajectory", "ate_pairs", "frames scored", "{:d}"),
    ("tracking", "frames", "frames", "{:d}"),
    ("tracking", "frames_lost", "frames lost", "{:d}"),
    ("tracking", "fps", "tracking [frames/s]", "{:.1f}"),
    ("live", "frames_received", "live: frames received", "{:d}"),
    ("live", "frames_processed", "live: frames processed", "{:d}"),
    ("live", "frames_dropped", "live: frames dropped (arrived while busy)", "{:d}"),
    ("live", "latency_ms_p50", "live: arrival to pose p50 [ms]", "{:.0f}"),
    ("live", "latency_ms_p95", "live: arrival to pose p95 [ms]", "{:.0f}"),
    ("live", "stopped_by", "live: input ended by", "{}"),
    ("rendering", "psnr", "PSNR [dB] at {res}", "{:.2f}"),
    ("rendering", "psnr_without_gross", "  PSNR without gross-error regions [dB]", "{:.2f}"),
    ("rendering", "gross_area_percent", "  ... regions' share of the image [%]", "{:.2f}"),
    ("rendering", "ssim", "SSIM at {res}", "{:.3f}"),
    ("rendering", "lpips", "LPIPS", "{}"),
    ("rendering", "depth_l1_cm", "Depth L1 [cm]", "{:.2f}"),
    ("rendering", "depth_median_cm", "  median depth error [cm]", "{:.2f}"),
    ("rendering", "depth_hole_cm", "  L1 from holes (nothing rendered) [cm]", "{:.2f}"),
    ("rendering", "depth_tail_cm", "  L1 from errors > 5 cm [cm]", "{:.2f}"),
    ("rendering", "depth_tail_step_cm", "  ... of it at depth discontinuities [cm]", "{:.2f}"),
    ("rendering", "normal_error_deg", "normal error [deg]", "{:.1f}"),
    ("rendering", "frames", "frames rendered", "{:d}"),
    ("rendering", "render_fps", "rendering [frames/s]", "{:.1f}"),
    ("mapping", "ply_fidelity", "gaussians.ply / map PSNR at keyframes [dB]", "ply"),
    ("mapping", "iterations", "mapping iterations", "{:d}"),
    ("mapping", "iterations_per_s", "mapping [iterations/s]", "{:.1f}"),
    ("mapping", "anchors", "anchors", "{:d}"),
    ("mapping", "gaussians", "Gaussians", "{:d}"),
    ("system", "wall_seconds", "wall time [s]", "{:.1f}"),
    ("system", "peak_rss_mb", "peak memory [MiB]", "{:.0f}"),
]


def _fmt(value, fmt: str) -> str:
    if fmt == "ply":  # the baked file under each keyframe's exposure, against the map's own render
        return (f"{_fmt(value.get('psnr_ply_exposed'), '{:.2f}')} / {_fmt(value.get('psnr_map'), '{:.2f}')} at "
                f"{value.get('width')}x{value.get('height')}")
    if isinstance(value, float) and math.isnan(value):
        return "n/a"
    try:
        return fmt.format(value)
    except (ValueError, TypeError):
        return str(value)


def metrics_table(metrics: dict, title: str = "ggfslam metrics") -> Table:
    """A two-column rich table of the metrics present in a ``metrics.json`` dict."""
    table = Table(title=Text(title) if title else None, show_header=True, header_style="bold")
    table.add_column("metric")
    table.add_column("value", justify="right")
    r = metrics.get("rendering", {})
    res = f"{r.get('width', '?')}x{r.get('height', '?')}"
    mp = metrics.get("mapping", {})
    rows = list(ROWS)
    if "train_width" in mp:
        rows.insert(next(i for i, row in enumerate(rows) if row[1] == "iterations"),
                    ("mapping", "train_width", "training resolution", "train"))
    if "live" in metrics:  # a live run has poses for the frames it processed only
        rows[0] = ("trajectory", "ate_rmse_cm", "ATE RMSE [cm] (frames processed)", "{:.2f}")
    for section, key, label, fmt in rows:
        if metrics.get(section, {}).get(key) is not None:
            value = metrics[section][key]
            if fmt == "train":
                value, fmt = f"{mp['train_width']}x{mp.get('train_height', '?')}", "{}"
            table.add_row(Text(label.replace("{res}", res)), _fmt(value, fmt))  # Text: '[cm]' is not markup
    return table


def print_metrics(metrics: dict, title: str = "ggfslam metrics", console: Console | None = None) -> None:
    """Print the metrics table."""
    console = console or Console()
    console.print(Text(title, style="bold"))  # above the table: a long title would wrap to the table's width
    console.print(metrics_table(metrics, title=""))
