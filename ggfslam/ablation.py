"""The paper's Table 5 ablation (``ggfslam bench``): base / +GGF / +GGF+GCGR on the sequences given.

Every variant runs the whole system on the same configuration, changing only the switches below; each run is a
normal run directory under ``out/<sequence>/<variant>`` (metrics.json, trajectory, map), and the table is saved
beside them as ``ablation.json``. An existing run directory is never replaced: a finished one is reused (its
metrics are read back), so an interrupted benchmark resumes where it stopped.
"""
from __future__ import annotations

import gc
import json
import logging
from pathlib import Path

from ggfslam.atomic import write_text_atomic
from ggfslam.config import Config, load_config
from ggfslam.errors import ConfigError, RunDirError
from ggfslam.rundir import METRICS_FILE, RUN_INFO_FILE

log = logging.getLogger("ggfslam")

VARIANTS: dict[str, dict[str, bool]] = {  # name -> (ggf.enabled, gcgr.enabled)
    "base": {"ggf.enabled": False, "gcgr.enabled": False},
    "ggf": {"ggf.enabled": True, "gcgr.enabled": False},
    "ggf_gcgr": {"ggf.enabled": True, "gcgr.enabled": True},
}
LABELS = {"base": "base", "ggf": "+GGF", "ggf_gcgr": "+GGF+GCGR"}
COLUMNS = ("psnr", "ssim", "depth_l1_cm", "ate_rmse_cm", "tracking_fps")


def variant_config(config_path: str | Path, variant: str, overrides: list[str]) -> Config:
    """The configuration of one variant: the file, the user's overrides, then the variant's switches."""
    if variant not in VARIANTS:
        raise ConfigError(f"unknown ablation variant {variant!r}; choose from {', '.join(VARIANTS)}")
    switches = [f"{k}={str(v).lower()}" for k, v in VARIANTS[variant].items()]
    return load_config(config_path, list(overrides) + switches)


def row_of(metrics: dict) -> dict:
    """The table's figures from a run's metrics.json (NaN where the run has none, e.g. no ground truth)."""
    nan = float("nan")
    r = metrics.get("rendering", {})
    res = f"{r['width']}x{r['height']}" if "width" in r and "height" in r else "-"
    return {"psnr": r.get("psnr", nan), "resolution": res, "ssim": r.get("ssim", nan),
            "depth_l1_cm": r.get("depth_l1_cm", nan),
            "ate_rmse_cm": metrics.get("trajectory", {}).get("ate_rmse_cm", nan),
            "tracking_fps": metrics.get("tracking", {}).get("fps", nan)}


def run_variant(cfg: Config, run_dir: Path) -> dict:
    """Run one variant into ``run_dir`` (a finished run there is read back instead); returns its metrics."""
    from ggfslam import slam
    from ggfslam.rundir import read_json

    if (run_dir / RUN_INFO_FILE).is_file() and read_json(run_dir / RUN_INFO_FILE).get("status") == "finished":
        log.info("%s: finished earlier, reusing its metrics", run_dir)
        return read_json(run_dir / METRICS_FILE)
    if run_dir.exists() and any(run_dir.iterdir()):
        raise RunDirError(f"{run_dir}: an unfinished run is there; resume it with `ggfslam run --resume --out "
                          f"{run_dir}` or move it away, then run the benchmark again")
    metrics = slam.run(cfg, run_dir, progress=False)
    gc.collect()  # one variant's map is garbage before the next one builds its own
    return metrics


def ablation(configs: list[str | Path], out: str | Path, variants: list[str] | None = None,
             overrides: list[str] | None = None) -> list[dict]:
    """Run every variant on every configured sequence; returns the table rows (also in out/ablation.json)."""
    variants = variants or list(VARIANTS)
    out = Path(out)
    # every configuration is checked before the first (long) run starts
    plan = [(Path(c), v, variant_config(c, v, overrides or [])) for c in configs for v in variants]
    rows = []
    for path, variant, cfg in plan:
        seq = cfg.name or path.stem
        metrics = run_variant(cfg, out / seq / variant)
        rows.append({"sequence": seq, "variant": variant, **row_of(metrics)})
        write_text_atomic(out / "ablation.json", json.dumps({"overrides": overrides or [], "rows": rows}, indent=1))
    return rows


def format_table(rows: list[dict]):
    """A rich Table of the rows, with the ATE change against each sequence's base (or first) variant."""
    from rich.table import Table

    table = Table("sequence", "variant", "PSNR dB at WxH", "SSIM", "depth L1 cm", "ATE RMSE cm", "ATE vs base",
                  "tracking fps", "fps vs base", title="ablation (paper Table 5)")
    ref = {}
    for r in rows:
        ref.setdefault(r["sequence"], r)
        if r["variant"] == "base":
            ref[r["sequence"]] = r
    for r in rows:
        b = ref[r["sequence"]]
        table.add_row(r["sequence"], LABELS.get(r["variant"], r["variant"]),
                      f"{r['psnr']:.2f} at {r.get('resolution', '-')}", f"{r['ssim']:.3f}", f"{r['depth_l1_cm']:.2f}", f"{r['ate_rmse_cm']:.2f}",
                      f"{100 * (r['ate_rmse_cm'] / b['ate_rmse_cm'] - 1):+.0f}%", f"{r['tracking_fps']:.1f}",
                      f"{100 * r['tracking_fps'] / b['tracking_fps']:.0f}%")
    return table


__all__ = ["VARIANTS", "ablation", "variant_config", "row_of", "format_table"]
