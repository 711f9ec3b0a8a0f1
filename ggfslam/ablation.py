"""The paper's Table 5 ablation (``ggfslam bench``): base / +GGF / +GGF+GCGR on the sequences given.

The ablation is a batch plan (``ggfslam.batch``): every variant runs the whole system on the same configuration,
changing only the switches below, as one ordinary run folder ``out/<sequence>/<variant>``; finished runs are
reused and interrupted ones resumed. ``configs/plans/table5.yaml`` is the same plan as a file for
``ggfslam batch``.
"""
from __future__ import annotations

from pathlib import Path

from ggfslam.batch.plan import Plan, build_plan
from ggfslam.batch.results import format_cell, format_spread, summarize
from ggfslam.errors import ConfigError

VARIANTS: dict[str, list[str]] = {  # name -> the switches of the variant
    "base": ["ggf.enabled=false", "gcgr.enabled=false"],
    "ggf": ["ggf.enabled=true", "gcgr.enabled=false"],
    "ggf_gcgr": ["ggf.enabled=true", "gcgr.enabled=true"],
}
LABELS = {"base": "base", "ggf": "+GGF", "ggf_gcgr": "+GGF+GCGR"}


REPEAT_JITTER_PX = 0.001
"""``tracking.keypoint_jitter_px`` of repeated ablation runs unless given: a thousandth of a pixel, far below the
keypoints' noise, so each seed is another draw of the trajectory rather than the same one."""


def ablation_plan(configs: list[str | Path], out: str | Path, variants: list[str] | None = None,
                  overrides: list[str] | None = None, num_cpus: float = 2, repeats: int = 1,
                  keypoint_jitter: float | None = None) -> Plan:
    """The ablation as a batch plan: ``variants`` (default all three) of every config, ``overrides`` in each; with
    ``repeats`` > 1, seeds 0 .. repeats - 1 of each, their keypoints jittered by ``keypoint_jitter`` px
    (default ``REPEAT_JITTER_PX``; the tracker reads the seed only through the jitter)."""
    variants = variants or list(VARIANTS)
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ConfigError(f"unknown ablation variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    jitter = keypoint_jitter if keypoint_jitter is not None else (REPEAT_JITTER_PX if repeats > 1 else 0.0)
    overrides = list(overrides or []) + ([f"tracking.keypoint_jitter_px={jitter}"] if jitter > 0 else [])
    data = {"name": "ablation (paper Table 5)", "sequences": [str(c) for c in configs], "set": overrides,
            "variants": {v: VARIANTS[v] for v in variants}, "num_cpus": num_cpus, "repeats": repeats}
    return build_plan(data, "ggfslam bench", Path.cwd(), Path(out).resolve())


def format_table(rows: list[dict]):
    """A rich Table of the rows, with the ATE change against each sequence's base (or first) variant; with repeated
    seeds one line per (sequence, variant): mean ± sample standard deviation over its finished runs."""
    from rich.table import Table

    repeated = any(r["seed"] is not None for r in rows)
    table = Table("sequence", "variant", "PSNR dB at WxH", "SSIM", "depth L1 cm", "ATE RMSE cm", "ATE vs base",
                  "tracking fps", "fps vs base", "runs" if repeated else "status", title="ablation (paper Table 5)")
    lines = summarize(rows) if repeated else rows
    ref = {}
    for r in lines:
        ref.setdefault(r["sequence"], r)
        if r["variant"] == "base":
            ref[r["sequence"]] = r

    def fig(r: dict, col: str, fmt: str) -> str:
        return format_spread(r, col, fmt) if repeated else format_cell(r[col], fmt)

    def val(r: dict, col: str) -> float:
        return r[col + "_mean"] if repeated else r[col]

    def change(a: float, b: float, fmt: str) -> str:
        return "-" if b == 0 else format_cell(a / b, fmt)  # NaN (no finished run) propagates to a dash

    for r in lines:
        b = ref[r["sequence"]]
        if repeated:
            status = f"{r['finished']}/{r['runs']}"
        else:
            status = r["status"] if r["status"] == "finished" else f"{r['status']}: {r.get('error') or ''}"
        table.add_row(r["sequence"], LABELS.get(r["variant"], r["variant"]),
                      f"{fig(r, 'psnr', '{:.2f}')} at {r.get('resolution', '-')}", fig(r, "ssim", "{:.3f}"),
                      fig(r, "depth_l1_cm", "{:.2f}"), fig(r, "ate_rmse_cm", "{:.2f}"),
                      change(val(r, "ate_rmse_cm") - val(b, "ate_rmse_cm"), val(b, "ate_rmse_cm"), "{:+.0%}"),
                      fig(r, "tracking_fps", "{:.1f}"),
                      change(val(r, "tracking_fps"), val(b, "tracking_fps"), "{:.0%}"), status)
    return table


__all__ = ["VARIANTS", "LABELS", "REPEAT_JITTER_PX", "ablation_plan", "format_table"]
