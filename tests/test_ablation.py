"""The ablation table (ggfslam bench): figures read from metrics.json, resolution beside PSNR, change vs base."""
from __future__ import annotations

import math

from rich.console import Console

from ggfslam.ablation import format_table, row_of


def _metrics(psnr: float, ate: float, fps: float) -> dict:
    return {"rendering": {"psnr": psnr, "ssim": 0.9, "depth_l1_cm": 1.5, "width": 640, "height": 480},
            "trajectory": {"ate_rmse_cm": ate}, "tracking": {"fps": fps}}


def test_rows_carry_the_resolution_and_the_change_against_base():
    rows = [{"sequence": "s", "variant": "base", **row_of(_metrics(24.0, 2.0, 20.0))},
            {"sequence": "s", "variant": "ggf_gcgr", **row_of(_metrics(24.5, 1.5, 15.0))}]
    assert rows[0]["resolution"] == "640x480"
    console = Console(record=True, width=200)
    console.print(format_table(rows))
    text = console.export_text()
    assert "24.50 at 640x480" in text and "-25%" in text and "75%" in text


def test_a_run_without_ground_truth_gives_nan_not_an_error():
    r = row_of({"tracking": {"fps": 10.0}})
    assert math.isnan(r["psnr"]) and math.isnan(r["ate_rmse_cm"]) and r["resolution"] == "-"
