"""The command line end to end on a 20-frame synthetic sequence, and its one-line errors on bad input."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ggfslam.cli import app

runner = CliRunner()
SMALL = ["--set", "dataset.synthetic.n_frames=20", "--set", "dataset.synthetic.width=320",
         "--set", "dataset.synthetic.height=240", "--set", "dataset.synthetic.depth_noise=false",
         "--set", "mapping.iterations_per_keyframe=10", "--set", "mapping.final_iterations=20",
         "--set", "mapping.eval_stride=2"]


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    path = tmp_path_factory.mktemp("cache")
    old = os.environ.get("GGFSLAM_CACHE")
    os.environ["GGFSLAM_CACHE"] = str(path)
    yield path
    if old is None:
        os.environ.pop("GGFSLAM_CACHE")
    else:
        os.environ["GGFSLAM_CACHE"] = old


@pytest.fixture(scope="module")
def synthetic_run(cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "syn"
    config = Path(__file__).parents[1] / "configs" / "synthetic" / "default.yaml"
    res = runner.invoke(app, ["run", str(config), "--out", str(out), "--no-progress", *SMALL])
    assert res.exit_code == 0, res.output
    return out, res.output


def test_run_writes_the_run_directory(synthetic_run):
    out, output = synthetic_run
    for name in ("config.yaml", "trajectory.txt", "groundtruth.txt", "tracking.txt", "metrics.json", "run.json",
                 "log.txt"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["trajectory"]["ate_pairs"] == 20  # every frame scored, not only keyframes
    # the baseline odometry on clean synthetic depth stays within a few centimetres over 20 frames
    assert metrics["trajectory"]["ate_rmse_cm"] < 3.0
    assert metrics["tracking"]["frames"] == 20 and metrics["tracking"]["fps"] > 0
    assert json.loads((out / "run.json").read_text())["status"] == "finished"
    assert "ATE RMSE" in output
    lines = [l for l in (out / "trajectory.txt").read_text().splitlines() if not l.startswith("#")]
    assert len(lines) == 20 and all(len(l.split()) == 8 for l in lines)
    # the Gaussian map: outputs and rendering metrics over every evaluated frame (not only keyframes)
    for name in ("gaussians.ply", "mesh.ply", "checkpoint.pt"):
        assert (out / name).is_file(), name
    r = metrics["rendering"]
    assert r["frames"] == 10 and len(r["per_frame"]) == 10 and {f["index"] for f in r["per_frame"]} == set(range(0, 20, 2))
    assert 15 < r["psnr"] < 60 and 0 < r["ssim"] <= 1 and r["depth_l1_cm"] >= 0
    assert metrics["mapping"]["anchors"] > 100 and metrics["mapping"]["gaussians"] > 100
    assert metrics["mapping"]["iterations"] >= 20 and metrics["mapping"]["iterations_per_s"] > 0
    assert "PSNR" in output and "Gaussians" in output


def test_demo_runs_its_own_sequence_and_prints_the_metrics(cache, tmp_path):
    """The README's first command, shortened: the demo renders its built-in sequence into the cache, runs the whole
    pipeline (the demo's ORB tracking, not the config file's) and prints the metrics table; --no-progress is
    accepted for logs and CI."""
    out = tmp_path / "demo"
    res = runner.invoke(app, ["demo", "--frames", "20", "--out", str(out), "--no-progress", *SMALL[2:]])
    assert res.exit_code == 0, res.output
    assert "ggfslam demo: synthetic room" in res.output and "ATE RMSE" in res.output and "PSNR" in res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["trajectory"]["ate_pairs"] == 20 and metrics["tracking"]["frames_lost"] == 0
    # the demo's 120 frames track to 0.09 cm (README); 20 noise-free frames at 320x240 stay under a centimetre
    assert metrics["trajectory"]["ate_rmse_cm"] < 1.0
    assert metrics["rendering"]["frames"] == 10 and 15 < metrics["rendering"]["psnr"] < 60
    assert json.loads((out / "run.json").read_text())["status"] == "finished"
    assert list((cache / "sequences").glob("procedural-*"))  # the sequence is kept for the next demo


def test_eval_recomputes_the_same_ate(synthetic_run):
    out, _ = synthetic_run
    before = json.loads((out / "metrics.json").read_text())["trajectory"]["ate_rmse_cm"]
    res = runner.invoke(app, ["eval", str(out)])
    assert res.exit_code == 0, res.output
    after = json.loads((out / "metrics.json").read_text())["trajectory"]["ate_rmse_cm"]
    assert after == pytest.approx(before, rel=1e-6)
    assert "ATE RMSE" in res.output


def test_eval_recomputes_the_same_rendering_metrics(synthetic_run):
    out, _ = synthetic_run
    before = json.loads((out / "metrics.json").read_text())["rendering"]
    res = runner.invoke(app, ["eval", str(out)])
    assert res.exit_code == 0, res.output
    after = json.loads((out / "metrics.json").read_text())["rendering"]
    for key in ("psnr", "ssim", "depth_l1_cm"):
        assert after[key] == pytest.approx(before[key], rel=1e-6), key
    assert "PSNR" in res.output


def test_render_writes_pngs_and_never_overwrites(synthetic_run, tmp_path):
    import cv2

    out, _ = synthetic_run
    dest = tmp_path / "views"
    res = runner.invoke(app, ["render", str(out), "--frames", "0:6:2", "--out", str(dest)])
    assert res.exit_code == 0, res.output
    rgb = sorted(dest.glob("*_rgb.png"))
    assert [p.name for p in rgb] == ["frame_000000_rgb.png", "frame_000002_rgb.png", "frame_000004_rgb.png"]
    img = cv2.imread(str(rgb[0]))
    depth = cv2.imread(str(dest / "frame_000000_depth.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320, 3) and depth.dtype == np.uint16 and depth.shape == (240, 320)
    assert np.median(depth[depth > 0]) > 500  # millimetres: the synthetic room is metres away
    again = runner.invoke(app, ["render", str(out), "--frames", "0:6:2", "--out", str(dest)])
    assert again.exit_code == 2 and "already there" in again.output
    path = runner.invoke(app, ["render", str(out), "--path", str(out / "keyframes.txt"), "--out", str(tmp_path / "p")])
    assert path.exit_code == 0, path.output
    assert len(list((tmp_path / "p").glob("view_*_rgb.png"))) == len(np.loadtxt(out / "keyframes.txt", ndmin=2))


def test_render_ply_shows_the_baked_file_as_the_map(synthetic_run, tmp_path):
    """``render --ply`` draws gaussians.ply itself; at the keyframes it matches the map's own render (the file
    carries the keyframes' median exposure, which on this sequence is the same for all), and metrics.json says
    so too."""
    import cv2

    from ggfslam.eval.image import psnr

    out, _ = synthetic_run
    res = runner.invoke(app, ["render", str(out), "--ply", "--out", str(tmp_path / "ply")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["render", str(out), "--out", str(tmp_path / "map")])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "ply").glob("*_rgb.png"))
    assert names and names == sorted(p.name for p in (tmp_path / "map").glob("*_rgb.png"))
    for name in names:
        a = cv2.imread(str(tmp_path / "ply" / name)).astype(np.float32) / 255
        b = cv2.imread(str(tmp_path / "map" / name)).astype(np.float32) / 255
        assert psnr(a, b) > 35.0, name
    fid = json.loads((out / "metrics.json").read_text())["mapping"]["ply_fidelity"]
    assert fid["keyframes"] == len(names)
    assert abs(fid["psnr_ply"] - fid["psnr_map"]) < 0.5 and abs(fid["psnr_ply_exposed"] - fid["psnr_map"]) < 0.1
    # the file along a path of the user's (here the keyframes' own poses)
    res = runner.invoke(app, ["render", str(out), "--ply", "--path", str(out / "keyframes.txt"),
                              "--out", str(tmp_path / "ply_path")])
    assert res.exit_code == 0, res.output
    assert len(list((tmp_path / "ply_path").glob("view_*_rgb.png"))) == len(names)
    # a run folder without the file: one clear line naming it
    (out / "gaussians.ply").rename(tmp_path / "kept.ply")
    try:
        bad = runner.invoke(app, ["render", str(out), "--ply", "--out", str(tmp_path / "ply2")])
    finally:
        (tmp_path / "kept.ply").rename(out / "gaussians.ply")
    assert bad.exit_code == 2 and "gaussians.ply missing" in bad.output


def test_resume_refuses_a_finished_run(synthetic_run):
    out, _ = synthetic_run
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "--no-progress"])
    assert res.exit_code == 2 and "finished" in res.output


def test_rerun_from_saved_config_is_deterministic(synthetic_run, tmp_path):
    out, _ = synthetic_run
    res = runner.invoke(app, ["run", str(out / "config.yaml"), "--out", str(tmp_path / "again"), "--no-progress"])
    assert res.exit_code == 0, res.output
    a = np.loadtxt(out / "trajectory.txt")
    b = np.loadtxt(tmp_path / "again" / "trajectory.txt")
    np.testing.assert_array_equal(a, b)
    # the map trains the same way too (metrics.json may have been rewritten by `eval`, which reads the poses
    # back from the rounded text trajectory, so compare the map itself)
    assert (out / "gaussians.ply").read_bytes() == (tmp_path / "again" / "gaussians.ply").read_bytes()


def test_existing_run_dir_is_not_overwritten(synthetic_run):
    out, _ = synthetic_run
    res = runner.invoke(app, ["run", str(out / "config.yaml"), "--out", str(out), "--no-progress"])
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert (out / "metrics.json").is_file()


def test_overwrite_refuses_a_folder_ggfslam_did_not_make(synthetic_run, tmp_path):
    out, _ = synthetic_run
    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.tex").write_text("important")
    res = runner.invoke(app, ["run", str(out / "config.yaml"), "--out", str(precious), "--overwrite"])
    assert res.exit_code == 2 and "not a ggfslam run directory" in res.output
    assert (precious / "chapter1.tex").read_text() == "important"


def test_synth_command_writes_tum_layout(cache, tmp_path):
    out = tmp_path / "seq"
    res = runner.invoke(app, ["synth", str(out), "--frames", "3", "--width", "64", "--height", "48"])
    assert res.exit_code == 0, res.output
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml", "mesh.ply"):
        assert (out / name).is_file(), name
    res = runner.invoke(app, ["synth", str(out), "--frames", "3", "--width", "64", "--height", "48"])
    assert res.exit_code == 2 and "--overwrite" in res.output


def test_run_on_a_sequence_folder_uses_the_built_in_defaults(cache, tmp_path):
    seq = tmp_path / "my_sensor_take"
    res = runner.invoke(app, ["synth", str(seq), "--frames", "12", "--width", "320", "--height", "240"])
    assert res.exit_code == 0, res.output
    out = tmp_path / "run"
    res = runner.invoke(app, ["run", str(seq), "--out", str(out), "--no-progress", "--set", "mapping.enabled=false"])
    assert res.exit_code == 0, res.output
    from ggfslam.config import SENSOR_MAPPING, Config, load_config

    saved = load_config(out / "config.yaml")  # the resolved config: the defaults, the folder, the override
    assert saved.name == "my_sensor_take"
    assert Path(saved.dataset.path) == seq.resolve() and saved.dataset.kind == "auto"
    assert saved.mapping.enabled is False
    assert saved.tracking == Config.model_validate({"dataset": {"path": "x"}}).tracking
    assert {k: getattr(saved.mapping, k) for k in SENSOR_MAPPING} == SENSOR_MAPPING  # a TUM-layout folder: sensor data
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["trajectory"]["ate_pairs"] == 12  # the folder's ground truth was found and every frame scored
    assert metrics["trajectory"]["ate_rmse_cm"] < 3.0


def _cli(*args, env=None):
    """Run the real ``ggfslam`` entry point in a subprocess (to see exactly what a user sees)."""
    return subprocess.run([sys.executable, "-m", "ggfslam.cli", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=120)


@pytest.mark.parametrize("case", ["missing_config", "unknown_key", "missing_dataset", "bad_depth", "not_a_run",
                                  "unknown_folder", "folder_unknown_key"])
def test_bad_input_is_one_line_without_traceback(case, tmp_path):
    cfg = tmp_path / "c.yaml"
    args = ["run", str(cfg), "--out", str(tmp_path / "out"), "--no-progress"]
    if case == "missing_config":
        needle = "config file not found"
    elif case == "unknown_key":
        cfg.write_text("dataset: {kind: tum, path: x}\nrender: {backnd: cpu}\n")
        needle = "unknown key 'render.backnd'"
    elif case == "missing_dataset":
        cfg.write_text(f"dataset: {{kind: tum, path: {tmp_path / 'nowhere'}}}\n")
        needle = "nowhere"
    elif case == "bad_depth":
        import cv2

        seq = tmp_path / "seq"
        (seq / "rgb").mkdir(parents=True)
        (seq / "depth").mkdir()
        for i in range(3):
            cv2.imwrite(str(seq / "rgb" / f"{i}.png"), np.zeros((8, 8, 3), np.uint8))
            cv2.imwrite(str(seq / "depth" / f"{i}.png"), np.zeros((8, 8), np.uint8))  # 8-bit: wrong
        (seq / "rgb.txt").write_text("".join(f"{i}.0 rgb/{i}.png\n" for i in range(3)))
        (seq / "depth.txt").write_text("".join(f"{i}.0 depth/{i}.png\n" for i in range(3)))
        cfg.write_text(f"dataset:\n  kind: tum\n  path: {seq}\n"
                       "  camera: {fx: 10, fy: 10, cx: 4, cy: 4, width: 8, height: 8}\n")
        needle = "16-bit"
    elif case == "unknown_folder":  # a folder instead of a config: its layout must be one the readers know
        (tmp_path / "photos").mkdir()
        args[1] = str(tmp_path / "photos")
        needle = "cannot tell the dataset format"
    elif case == "folder_unknown_key":
        (tmp_path / "photos").mkdir()
        args[1] = str(tmp_path / "photos")
        args += ["--set", "dataset.strid=2"]
        needle = "unknown key 'dataset.strid'"
    else:
        args = ["eval", str(tmp_path)]
        needle = "not a ggfslam run directory"
    res = _cli(*args)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr and needle in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
