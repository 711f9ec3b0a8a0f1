"""The paper's Table 5 ablation (``ggfslam bench``): base / +GGF / +GGF+GCGR on the sequences given.

The ablation is a batch plan (``ggfslam.batch``): every variant runs the whole system on the same configuration,
changing only the switches below, as one ordinary run folder ``out/<sequence>/<variant>``; finished runs are
reused and interrupted ones resumed. ``configs/plans/table5.yaml`` is the same plan as a file for
``ggfslam batch``.
"""
from __future__ import annotations

from pathlib import Path

from ggfslam.batch.plan import Plan, build_plan
from ggfslam.errors import ConfigError

VARIANTS: dict[str, list[str]] = {  # name -> the switches of the variant
    "base": ["ggf.enabled=false", "gcgr.enabled=false"],
    "ggf": ["ggf.enabled=true", "gcgr.enabled=false"],
    "ggf_gcgr": ["ggf.enabled=true", "gcgr.enabled=true"],
}
LABELS = {"base": "base", "ggf": "+GGF", "ggf_gcgr": "+GGF+GCGR"}


def ablation_plan(configs: list[str | Path], out: str | Path, variants: list[str] | None = None,
                  overrides: list[str] | None = None, num_cpus: float = 2) -> Plan:
    """The ablation as a batch plan: ``variants`` (default all three) of every config, ``overrides`` in each."""
    variants = variants or list(VARIANTS)
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ConfigError(f"unknown ablation variant {unknown[0]!r}; choose from {', '.join(VARIANTS)}")
    data = {"name": "ablation (paper Table 5)", "sequences": [str(c) for c in configs], "set": list(overrides or []),
            "variants": {v: VARIANTS[v] for v in variants}, "num_cpus": num_cpus}
    return build_plan(data, "ggfslam bench", Path.cwd(), Path(out).resolve())


def format_table(rows: list[dict]):
    """A rich Table of the rows, with the ATE change against each sequence's base (or first) variant."""
    from rich.table import Table

    table = Table("sequence", "variant", "PSNR dB at WxH", "SSIM", "depth L1 cm", "ATE RMSE cm", "ATE vs base",
                  "tracking fps", "fps vs base", "status", title="ablation (paper Table 5)")
    ref = {}
    for r in rows:
        ref.setdefault(r["sequence"], r)
        if r["variant"] == "base":
            ref[r["sequence"]] = r
    for r in rows:
        b = ref[r["sequence"]]
        table.add_row(r["sequence"], LABELS.get(r["variant"], r["variant"]),
                      f"{r['psnr']:.2f} at {r.get('resolution', '-')}", f"{r['ssim']:.3f}", f"{r['depth_l1_cm']:.2f}",
                      f"{r['ate_rmse_cm']:.2f}", f"{100 * (r['ate_rmse_cm'] / b['ate_rmse_cm'] - 1):+.0f}%",
                      f"{r['tracking_fps']:.1f}", f"{100 * r['tracking_fps'] / b['tracking_fps']:.0f}%",
                      r["status"] if r["status"] == "finished" else f"{r['status']}: {r.get('error') or ''}")
    return table


__all__ = ["VARIANTS", "LABELS", "ablation_plan", "format_table"]
