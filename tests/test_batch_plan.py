"""Batch plans and results without Ray: expansion (globs, variants, sweeps, seeds), errors, run folder states,
results files and the summary over seeds, the synthetic cache's lock."""
from __future__ import annotations

import csv
import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from ggfslam.ablation import VARIANTS, ablation_plan, format_table
from ggfslam.batch.plan import load_plan
from ggfslam.batch.results import make_row, metric_columns, summarize, write_results
from ggfslam.batch.task import run_state
from ggfslam.config import load_config, save_config
from ggfslam.errors import ConfigError

REPO = Path(__file__).parents[1]


def _configs(folder: Path) -> Path:
    """Two sequence configs in ``folder/seq`` and a broken one."""
    seq = folder / "seq"
    seq.mkdir(parents=True)
    for name in ("alpha", "beta"):
        (seq / f"{name}.yaml").write_text(f"name: {name}\ndataset: {{kind: synthetic}}\n")
    (folder / "broken.yaml").write_text("name: broken\ndataset: {kind: synthetic, synthetic: {trajectory: spiral}}\n")
    return seq


def _plan(tmp_path, text: str, out="out"):
    (tmp_path / "plans").mkdir(exist_ok=True)
    path = tmp_path / "plans" / "p.yaml"
    path.write_text(text)
    return load_plan(path, tmp_path / out)


def test_globs_variants_and_seeds_expand_in_order_with_overrides_applied_last_wins(tmp_path):
    _configs(tmp_path)
    plan = _plan(tmp_path, """
sequences: ["../seq/*.yaml"]
set: [tracking.n_features=900, mapping.mesh=false]
variants:
  small: [tracking.n_features=700]
  big: [tracking.n_features=2000]
repeats: 2
num_cpus: 2
""")
    assert [r.key for r in plan.runs] == [f"{s}/{v}/seed{k}" for s in ("alpha", "beta") for v in ("small", "big")
                                          for k in (0, 1)]
    r = plan.runs[2]  # alpha/big/seed0
    assert r.config.tracking.n_features == 2000 and r.config.runtime.seed == 0 and r.config.mapping.mesh is False
    assert plan.runs[3].config.runtime.seed == 1
    assert r.run_dir == (tmp_path / "out" / "alpha" / "big" / "seed0").resolve()
    assert r.config_path == (tmp_path / "seq" / "alpha.yaml").resolve() and r.threads == 2
    assert plan.name == "p" and plan.spec["variants"] == {"small": ["tracking.n_features=700"],
                                                          "big": ["tracking.n_features=2000"]}


def test_a_sweep_is_a_product_or_a_zip_of_values_and_names_its_variants(tmp_path):
    _configs(tmp_path)
    product = _plan(tmp_path, """
sequences: [{config: ../seq/alpha.yaml, name: a}]
sweep: {values: {tracking.n_features: [800, 1600], mapping.train_width: [160, 320]}}
seeds: [3, 7]
""")
    labels = sorted({r.variant for r in product.runs})
    assert labels == ["n_features=1600,train_width=160", "n_features=1600,train_width=320",
                      "n_features=800,train_width=160", "n_features=800,train_width=320"]
    assert len(product.runs) == 8 and {r.seed for r in product.runs} == {3, 7}
    run = next(r for r in product.runs if r.variant == "n_features=800,train_width=320" and r.seed == 7)
    assert (run.config.tracking.n_features, run.config.mapping.train_width, run.config.runtime.seed) == (800, 320, 7)
    zipped = _plan(tmp_path, """
sequences: [../seq/alpha.yaml]
variants: {base: [ggf.enabled=false], full: [ggf.enabled=true]}
sweep: {mode: zip, values: {tracking.n_features: [800, 1600], mapping.train_width: [160, 320]}}
""")
    assert [r.key for r in zipped.runs] == ["alpha/base+n_features=800,train_width=160",
                                           "alpha/base+n_features=1600,train_width=320",
                                           "alpha/full+n_features=800,train_width=160",
                                           "alpha/full+n_features=1600,train_width=320"]
    assert zipped.runs[3].config.ggf.enabled and zipped.runs[3].config.mapping.train_width == 320
    assert all(r.seed is None for r in zipped.runs)  # one seed: no seed level in the folders


def test_a_broken_sequence_config_is_its_runs_error_not_the_plans(tmp_path):
    _configs(tmp_path)
    plan = _plan(tmp_path, "sequences: [../seq/alpha.yaml, ../broken.yaml]\nvariants: {a: [], b: []}\n")
    broken = [r for r in plan.runs if r.sequence == "broken"]
    assert len(broken) == 2 and all(r.config is None for r in broken)
    assert "broken.yaml: dataset.synthetic.trajectory" in broken[0].error and "'spiral'" in broken[0].error
    assert all(r.error is None and r.config is not None for r in plan.runs if r.sequence == "alpha")
    # a variant's bad value is that run's error only
    plan = _plan(tmp_path, "sequences: [../seq/alpha.yaml]\nvariants: {ok: [], bad: [tracking.n_features=lots]}\n")
    assert plan.runs[0].error is None and "tracking.n_features" in plan.runs[1].error


@pytest.mark.parametrize("text, message", [
    ("sequences: [../seq/*.yml]\n", r"sequences\[0\]: '../seq/\*.yml' matches no file"),
    ("sequences: [../seq/none.yaml]\n", r"sequences\[0\]: config file .*none.yaml not found"),
    ("sequences: [../seq/alpha.yaml]\nrepeat: 2\n", r"unknown key 'repeat'; valid keys here: .*repeats"),
    ("sequences: [../seq/alpha.yaml]\nsweep: {mode: zip, values: {a.b: [1, 2], c.d: [1]}}\n",
     "zip needs lists of one length; got a.b: 2, c.d: 1"),
    ("sequences: [../seq/alpha.yaml]\nset: [tracking.n_features]\n", r"set: --set 'tracking.n_features': expected"),
    ("sequences: [../seq/alpha.yaml, {config: ../seq/beta.yaml, name: alpha}]\n", "two sequences are named 'alpha'"),
    ("sequences: []\n", "sequences: List should have at least 1 item"),
    ("sequences: [../seq/alpha.yaml]\nnum_cpus: 0\n", "num_cpus: Input should be greater than 0"),
    ("sequences: [../seq/alpha.yaml\n", r"p.yaml:\d+: not valid YAML"),
    ("sequences: [../seq/alpha.yaml]\nrepeats: 2\nseeds: [1, 2]\n", "give repeats or seeds, not both"),
    ("sequences: [../seq/alpha.yaml]\nvariants: {a b: [], a_b: []}\n", "variant folder name 'a_b' stands for two"),
])
def test_a_bad_plan_fails_with_one_line_naming_the_file_and_field(tmp_path, text, message):
    _configs(tmp_path)
    with pytest.raises(ConfigError, match=message) as e:
        _plan(tmp_path, text)
    assert "p.yaml" in str(e.value) and "\n" not in str(e.value)


def test_run_folder_states_new_finished_resume_and_conflict(tmp_path):
    cfg = load_config(REPO / "configs" / "synthetic" / "default.yaml")
    run = tmp_path / "run"
    assert run_state(run, cfg)[0] == "new"
    run.mkdir()
    assert run_state(run, cfg)[0] == "new"  # empty
    (run / "notes.txt").write_text("mine")
    state, why = run_state(run, cfg)
    assert state == "conflict" and "not a ggfslam run" in why
    (run / "notes.txt").unlink()
    save_config(cfg, run / "config.yaml")
    (run / "run.json").write_text(json.dumps({"status": "interrupted", "resume_from_frame": 12}))
    assert run_state(run, cfg) == ("resume", "resuming (interrupted, from frame 12)")
    (run / "run.json").write_text(json.dumps({"status": "finished"}))
    (run / "metrics.json").write_text("{}")
    assert run_state(run, cfg)[0] == "finished"
    # the thread count is how a run was executed, not what it computed: the finished run is still this one
    threads = cfg.model_copy(deep=True)
    threads.runtime.num_threads = 3
    assert run_state(run, threads)[0] == "finished"
    other = cfg.model_copy(deep=True)
    other.tracking.n_features = 99
    state, why = run_state(run, other)
    assert state == "conflict" and "tracking.n_features differ" in why


def _row(spec_key: str, seed, ate, psnr, status="finished"):
    from types import SimpleNamespace

    seq, var = spec_key.split("/")
    spec = SimpleNamespace(sequence=seq, variant=var, seed=seed, run_dir=Path("/r"), key=f"{spec_key}/{seed}")
    metrics = {"trajectory": {"ate_rmse_cm": ate, "rpe_trans_rmse_cm": 0.5, "rpe_rot_rmse_deg": 0.1},
               "rendering": {"psnr": psnr, "ssim": 0.9, "depth_l1_cm": 1.0, "width": 640, "height": 480},
               "tracking": {"fps": 20.0}, "system": {"wall_seconds": 100.0, "peak_rss_mb": 2048.0},
               "sequence": {"frames": 50}}
    return make_row(spec, status, "ran", metrics if status == "finished" else None,
                    None if status == "finished" else "ValueError: x", 1)


def test_results_files_and_the_mean_and_spread_over_seeds(tmp_path):
    rows = [_row("s/a", 0, 2.0, 24.0), _row("s/a", 1, 3.0, 26.0), _row("s/a", 2, 0, 0, status="failed"),
            _row("s/b", 0, 1.0, 25.0)]
    (s_a, s_b) = summarize(rows)
    assert (s_a["runs"], s_a["finished"]) == (3, 2)
    assert s_a["ate_rmse_cm_mean"] == 2.5 and s_a["ate_rmse_cm_std"] == pytest.approx(np.std([2.0, 3.0], ddof=1))
    assert s_a["psnr_mean"] == 25.0 and s_a["resolution"] == "640x480"
    assert s_b["ate_rmse_cm_std"] == 0.0 and s_b["finished"] == 1
    write_results(tmp_path, "p", rows)
    with open(tmp_path / "results.csv") as f:
        table = list(csv.DictReader(f))
    assert len(table) == 4 and table[0]["ate_rmse_cm"] == "2.0" and table[0]["resolution"] == "640x480"
    assert table[2]["status"] == "failed" and table[2]["error"] == "ValueError: x" and table[2]["psnr"] == ""
    doc = json.loads((tmp_path / "results.json").read_text())  # strict JSON: NaN written as null
    assert doc["rows"][2]["psnr"] is None and doc["summary"][0]["psnr_mean"] == 25.0


def test_a_run_without_ground_truth_gives_nan_not_an_error():
    r = metric_columns({"tracking": {"fps": 10.0}})
    assert math.isnan(r["psnr"]) and math.isnan(r["ate_rmse_cm"]) and r["resolution"] == "-"
    assert r["tracking_fps"] == 10.0


def test_the_ablation_table_carries_the_resolution_and_the_change_against_base():
    from rich.console import Console

    base, full = _row("s/base", None, 2.0, 24.0), _row("s/ggf_gcgr", None, 1.5, 24.5)
    full["tracking_fps"] = 15.0
    console = Console(record=True, width=200)
    console.print(format_table([base, full]))
    text = console.export_text()
    assert "24.50 at 640x480" in text and "-25%" in text and "75%" in text


def test_bench_is_the_table5_plan(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    configs = ["configs/tum/fr3_cabinet_kf.yaml", "configs/7scenes/redkitchen_500_registered.yaml"]
    bench = ablation_plan(configs, tmp_path / "out")
    file = load_plan(REPO / "configs" / "plans" / "table5.yaml", tmp_path / "out")
    assert [(r.key, r.overrides, r.config_path, r.num_cpus) for r in bench.runs] == \
           [(r.key, r.overrides, r.config_path, r.num_cpus) for r in file.runs]
    assert [r.key for r in bench.runs] == [f"{s}/{v}" for s in ("fr3_cabinet_kf", "7scenes_redkitchen_500_registered")
                                           for v in VARIANTS]
    assert bench.runs[5].config.gcgr.enabled and not bench.runs[3].config.ggf.enabled
    with pytest.raises(ConfigError, match="unknown ablation variant 'gcgr'"):
        ablation_plan(configs, tmp_path / "out", ["gcgr"])


def test_repeated_bench_runs_draw_different_trajectories_through_the_keypoint_jitter(tmp_path, monkeypatch):
    monkeypatch.chdir(REPO)
    configs = ["configs/tum/fr3_cabinet_kf.yaml"]
    plan = ablation_plan(configs, tmp_path / "out", ["base", "ggf_gcgr"], repeats=3)
    assert [(r.key, r.seed) for r in plan.runs] == [(f"fr3_cabinet_kf/{v}/seed{k}", k)
                                                    for v in ("base", "ggf_gcgr") for k in range(3)]
    assert all(r.config.tracking.keypoint_jitter_px == 0.001 and r.config.runtime.seed == r.seed for r in plan.runs)
    # one run each: no jitter unless asked for; an explicit 0 keeps repeated runs on one trajectory
    assert all(r.config.tracking.keypoint_jitter_px == 0 for r in ablation_plan(configs, tmp_path / "o1").runs)
    plan0 = ablation_plan(configs, tmp_path / "o2", ["base"], repeats=2, keypoint_jitter=0.0)
    assert all(r.config.tracking.keypoint_jitter_px == 0 for r in plan0.runs)
    with pytest.raises(ConfigError, match="repeats: Input should be greater than or equal to 1"):  # the plan's check
        ablation_plan(configs, tmp_path / "o3", repeats=0)


def test_the_repeated_ablation_table_compares_means():
    from rich.console import Console

    rows = [_row("s/base", 0, 2.0, 24.0), _row("s/base", 1, 3.0, 25.0),
            _row("s/ggf_gcgr", 0, 2.0, 24.0), _row("s/ggf_gcgr", 1, 2.0, 24.0), _row("s/ggf_gcgr", 2, 2.0, 24.0),
            _row("s/ggf", 0, None, None, status="failed")]
    console = Console(record=True, width=220)
    console.print(format_table(rows))
    text = console.export_text()
    lines = [ln for ln in text.splitlines() if ln.startswith("│ s ")]
    assert len(lines) == 3  # one line per variant
    assert "2.50 ± 0.71" in lines[0] and "24.50 ± 0.71 at 640x480" in lines[0] and "2/2" in lines[0]
    assert "2.00 ± 0.00" in lines[1] and "-20%" in lines[1] and "3/3" in lines[1]
    assert "0/1" in lines[2] and "nan" not in lines[2]  # a variant with no finished run: dashes


@pytest.mark.parametrize("name", ["table5.yaml", "example_sweep.yaml"])
def test_the_shipped_plans_validate(tmp_path, name, monkeypatch):
    monkeypatch.setenv("GGFSLAM_DATA", str(tmp_path))  # configs name their data through it; not read here
    plan = load_plan(REPO / "configs" / "plans" / name, tmp_path)
    assert plan.runs and all(r.error is None for r in plan.runs)


def test_the_shipped_example_plan_expands(tmp_path):
    plan = load_plan(REPO / "configs" / "plans" / "example_sweep.yaml", tmp_path)
    assert len(plan.runs) == 8 and all(r.error is None for r in plan.runs)
    assert {r.config.dataset.synthetic.n_frames for r in plan.runs} == {60}


def test_a_synthetic_sequence_wanted_by_several_runs_at_once_is_rendered_once(tmp_path, monkeypatch):
    from ggfslam.config import config_from_dict
    from ggfslam.data import sources, synthetic

    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    calls = []
    real = synthetic.write_synthetic_sequence

    def slow(*args, **kwargs):
        calls.append(1)
        time.sleep(0.3)  # long enough for the other thread to arrive while this one renders
        return real(*args, **kwargs)

    monkeypatch.setattr(synthetic, "write_synthetic_sequence", slow)
    syn = config_from_dict({"dataset": {"kind": "synthetic", "synthetic": {"n_frames": 3, "width": 64,
                                                                          "height": 48}}}).dataset.synthetic
    paths = []
    threads = [threading.Thread(target=lambda: paths.append(sources.generate_synthetic(syn))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and len(set(paths)) == 1 and (paths[0] / "rgb.txt").is_file()
    assert [p.name for p in paths[0].parent.iterdir() if p.name.startswith(".partial")] == []
    assert yaml.safe_load((paths[0] / "camera.yaml").read_text())["width"] == 64


def test_a_finished_run_with_a_damaged_metrics_file_is_a_failed_row_and_stays_as_it_is(tmp_path):
    from rich.console import Console

    from ggfslam.batch import run_batch

    _configs(tmp_path)
    plan = _plan(tmp_path, "sequences: [../seq/alpha.yaml]\n")
    run = plan.runs[0].run_dir
    run.mkdir(parents=True)
    save_config(plan.runs[0].config, run / "config.yaml")
    (run / "run.json").write_text(json.dumps({"status": "finished"}))
    (run / "metrics.json").write_text("{not json")
    (row,) = run_batch(plan, tmp_path / "out", console=Console(file=open(tmp_path / "log.txt", "w")))
    assert row["status"] == "failed" and "metrics.json:1: not valid JSON" in row["error"]
    assert (run / "metrics.json").read_text() == "{not json"
    assert json.loads((tmp_path / "out" / "results.json").read_text())["rows"][0]["status"] == "failed"


def test_a_folder_of_the_users_is_not_taken_for_a_batch_folder(tmp_path):
    from ggfslam.batch import run_batch
    from ggfslam.errors import BatchError

    _configs(tmp_path)
    plan = _plan(tmp_path, "sequences: [../seq/alpha.yaml]\n", out="mine")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "results.csv").write_text("my figures")
    with pytest.raises(BatchError, match="not a batch folder .* and not empty"):
        run_batch(plan, tmp_path / "mine")
    assert (tmp_path / "mine" / "results.csv").read_text() == "my figures"
