"""The web viewer: a run folder's layers (values checked against the run's own files and metrics), the click picker,
one-line errors, and the page itself in a real browser (Debian's Chromium driven by Playwright)."""
from __future__ import annotations

import json
import os
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from ggfslam.cli import app
from ggfslam.errors import ViewerError
from ggfslam.viewer.layers import covariances, load_run_layers
from ggfslam.viewer.scene import Pickable, pick
from tests.conftest import run_synthetic

CHROMIUM = os.environ.get("GGFSLAM_CHROMIUM", "/usr/bin/chromium")
ARTIFACTS = Path(os.environ.get("GGFSLAM_TEST_ARTIFACTS", Path(__file__).parents[1] / "test-artifacts"))
# Chromium as root in a container, without a GPU (SwiftShader's WebGL) and without reaching out to the network
CHROMIUM_ARGS = ["--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]
VIEWPORT = {"width": 1000, "height": 700}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A short synthetic run with the field and GCGR on, so every layer has something to show; or the run named
    by GGFSLAM_VIEWER_RUN (the README's screenshot is taken of a demo run that way)."""
    if os.environ.get("GGFSLAM_VIEWER_RUN"):
        return Path(os.environ["GGFSLAM_VIEWER_RUN"])
    return run_synthetic(tmp_path_factory, "viewer", {
        "dataset": {"kind": "synthetic", "synthetic": {"n_frames": 24, "width": 320, "height": 240,
                                                      "depth_noise": True}},
        "tracking": {"keyframe_max_frames": 6}, "gcgr": {"enabled": True},
        "mapping": {"train_width": 160, "iterations_per_keyframe": 30, "final_iterations": 60, "eval_stride": 8}})


@pytest.fixture(scope="module")
def layers(run_dir):
    return load_run_layers(run_dir)


def test_layers_match_the_run_files(run_dir, layers):
    from ggfslam.gaussians.ply import read_gaussians_ply

    assert layers.problems == {}
    ply = read_gaussians_ply(run_dir / "gaussians.ply")
    s = layers.splats
    assert len(s.means) == len(ply["means"]) == s.total
    np.testing.assert_allclose(s.means, ply["means"])
    # the planar colours are gaussians_planarity.ply's, Gaussian for Gaussian
    planar = read_gaussians_ply(run_dir / "gaussians_planarity.ply")
    np.testing.assert_allclose(s.planar_colors, np.clip(planar["colors"], 0, 1))
    assert len(layers.mesh.faces) > 100
    graph = json.loads((run_dir / "graph.json").read_text())
    assert len(layers.keyframes.poses) == len(graph["keyframes"]) == len(layers.keyframes.images)
    assert all(im is not None and im.shape[1] == 160 for im in layers.keyframes.images)
    assert len(layers.graph.landmarks) == len(graph["landmarks"])
    kinds = {e.kind for e in layers.graph.edges}
    assert "covisibility" in kinds
    assert layers.graph.gcgr, "GCGR factors in graph.json are drawn"
    for f in layers.graph.gcgr:  # lifted pixels lie in front of their keyframe, at the scene's depth
        T = layers.keyframes.poses[list(layers.keyframes.ids).index(f["kf"])]
        z = (f["points"] - T[:3, 3]) @ T[:3, 2]
        assert len(z) > 0 and np.all(z > 0.1) and np.all(z < 10)


def test_trajectory_error_is_the_ate(run_dir, layers):
    """The per-frame colours are the ATE's own errors: their RMS is metrics.json's ATE RMSE, and the ground truth,
    brought into the map's frame, sits on the estimate."""
    t = layers.trajectories
    metrics = json.loads((run_dir / "metrics.json").read_text())["trajectory"]
    assert np.isfinite(t.error_m).all()
    rms_cm = 100 * np.sqrt(np.mean(t.error_m ** 2))
    assert rms_cm == pytest.approx(metrics["ate_rmse_cm"], rel=1e-6)
    assert 100 * t.ate_rmse_m == pytest.approx(metrics["ate_rmse_cm"], rel=1e-6)
    assert np.abs(t.est[:, :3, 3] - t.gt[:, :3, 3]).max() < 0.05


def test_covariances_from_quaternions_and_scales():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    R = Rotation.random(5, random_state=1)
    xyzw = R.as_quat()
    s = rng.uniform(0.01, 0.2, (5, 3))
    cov = covariances(xyzw[:, [3, 0, 1, 2]], s)
    expect = R.as_matrix() @ (s[:, :, None] ** 2 * np.eye(3)) @ R.as_matrix().transpose(0, 2, 1)
    np.testing.assert_allclose(cov, expect, rtol=1e-5, atol=1e-9)


def test_pick_names_the_element_under_the_click(layers):
    g = layers.graph
    origin = g.kf_position[min(g.kf_position)]
    target = int(np.argmax(g.landmark_error))
    p = Pickable("landmarks", g.landmarks, np.arange(len(g.landmarks)), lambda i: f"l{g.landmark_ids[i]}")
    hit = pick([p], origin, g.landmarks[target] - origin)
    assert hit is not None and hit[0].describe(hit[1]) == f"l{g.landmark_ids[target]}"
    away = g.landmarks[target] - origin
    away = np.cross(away, [0.0, 0.0, 1.0]) + np.cross(away, [0.0, 1.0, 0.0])  # perpendicular-ish: nothing there
    assert pick([Pickable("x", g.landmarks[target:target + 1], np.zeros(1, int), str)], origin, away) is None


def test_a_missing_layer_is_one_line_and_the_others_still_load(run_dir, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy, ignore=shutil.ignore_patterns("checkpoint.pt", "keyframes"))
    (copy / "mesh.ply").unlink()
    (copy / "graph.json").write_text("{not json")
    L = load_run_layers(copy)
    assert set(L.problems) == {"mesh", "factor graph"}
    assert "mesh.ply missing" in L.problems["mesh"] and "graph.json" in L.problems["factor graph"]
    assert all("\n" not in v for v in L.problems.values())
    assert L.splats is not None and L.trajectories is not None and L.keyframes is not None
    assert all(im is None for im in L.keyframes.images)  # images were not copied; the frustums stay


def test_taken_port_is_one_clear_line(run_dir):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        res = CliRunner().invoke(app, ["view", str(run_dir), "--port", str(port)])
        assert res.exit_code == 2
        assert f"port {port} on 127.0.0.1 is taken" in res.output and "--port" in res.output
        from ggfslam.viewer.app import check_port
        with pytest.raises(ViewerError, match="taken"):
            check_port("127.0.0.1", port)


def test_frame_slider_shows_the_render_and_the_input_there(run_dir, layers):
    """Moving to a frame renders the map at its estimated pose beside that frame's input image."""
    from ggfslam.viewer.app import serve_run

    server, scene = serve_run(run_dir, port=0)
    try:
        row = 7
        scene.show_frame(row)
        shown = scene._frame_images[0].image
        assert np.array_equal(shown, scene.frames.render(row))
        image, caption = scene.frames.input_image(row)
        assert np.array_equal(scene._frame_images[1].image, image) and caption == f"input frame {row}"
        err = layers.trajectories.error_m[row]
        assert f"position error {100 * err:.2f} cm" in scene.frame_caption.content
        # the render is the map at that pose: closer to the input image there than to the input half the
        # sequence away (a short run at 160 px: a rough map with holes, white like the page's background)
        from ggfslam.eval.image import psnr

        other, _ = scene.frames.input_image(row + 12)
        here = psnr(shown.astype(np.float32) / 255, image.astype(np.float32) / 255)
        there = psnr(shown.astype(np.float32) / 255, other.astype(np.float32) / 255)
        print(f"render vs input: {here:.2f} dB at its frame, {there:.2f} dB 12 frames away")
        assert here > there + 1.0
    finally:
        server.stop()


def test_live_viewer_follows_a_run_and_a_plain_run_imports_none_of_it(tmp_path):
    """With an observer the viewer draws poses and the map while frames are tracked, then the finished folder;
    without one, no module of the viewer (or viser) is imported."""
    import subprocess
    import sys

    code = (
        "import sys, json\n"
        "from ggfslam import slam\n"
        "from ggfslam.config import config_from_dict\n"
        "cfg = config_from_dict({'name': 'plain', 'dataset': {'kind': 'synthetic', 'synthetic': {'n_frames': 6,"
        " 'width': 160, 'height': 120}}, 'mapping': {'enabled': False}}, 'test')\n"
        f"slam.run(cfg, {str(tmp_path / 'plain')!r}, progress=False)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('viser', 'ggfslam.viewer')))))\n")
    env = {**os.environ, "GGFSLAM_CACHE": str(tmp_path / "cache")}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout.strip().splitlines()[-1]) == []

    from ggfslam import slam
    from ggfslam.config import config_from_dict
    from ggfslam.viewer.live import LiveViewer

    mp = pytest.MonkeyPatch()
    mp.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    cfg = config_from_dict({"name": "live", "dataset": {"kind": "synthetic", "synthetic": {
        "n_frames": 16, "width": 160, "height": 120}}, "tracking": {"keyframe_max_frames": 4},
        "mapping": {"iterations_per_keyframe": 60, "final_iterations": 20, "eval_stride": 8}}, "test")
    viewer = LiveViewer("127.0.0.1", 0, pose_period=0.2, map_period=0.5, map_share=1.0)
    try:
        slam.run(cfg, tmp_path / "live", progress=False, observer=viewer)
        assert viewer.updates["poses"] >= 2 and viewer.updates["maps"] >= 1, viewer.updates
        st = viewer.status()
        # the finished folder, every layer, a frustum per keyframe, the slider over every frame
        assert st["run_dir"] == str(tmp_path / "live") and st["problems"] == {}
        assert st["layers"] == ["splats", "mesh", "trajectories", "keyframes", "graph"]
        assert st["frustums"] == st["keyframes"] and len(st["keyframes"]) >= 3 and st["frustums_visible"]
        assert st["frames"] == 16 and st["slider_max"] == 15
    finally:
        viewer.close()
        mp.undo()


def _canvas_pixels(png: bytes) -> np.ndarray:
    """The screenshot as float RGB [H, W, 3] in [0, 1], cut left of the GUI panel."""
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
    return img[:, : int(0.62 * img.shape[1])]


def _centre(img: np.ndarray, frac_w: float, frac_h: float, cx: float | None = None) -> np.ndarray:
    h, w = img.shape[:2]
    cx = w / 2 if cx is None else cx
    return img[int(h / 2 - frac_h * h / 2): int(h / 2 + frac_h * h / 2),
               int(cx - frac_w * h / 2): int(cx + frac_w * h / 2)]


def _foreground(img: np.ndarray) -> np.ndarray:
    return np.abs(img - 1.0).max(axis=-1) > 0.06  # not viser's white background


@pytest.mark.skipif(not Path(CHROMIUM).is_file(), reason=f"no Chromium at {CHROMIUM} (Debian: apt-get install "
                    "chromium; or set GGFSLAM_CHROMIUM)")
def test_viewer_page_in_chromium(run_dir, layers):
    """The page in a real browser: it shows the map from the first keyframe's viewpoint in the map's colours, and
    switching the map layer off changes the picture. The screenshot is kept in test-artifacts/."""
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install "
                                     "playwright)")
    from ggfslam.viewer.app import serve_run

    server, scene = serve_run(run_dir, port=0)
    try:
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=VIEWPORT, device_scale_factor=1)
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            page.wait_for_selector("canvas", timeout=60_000)
            shot = _wait_for(page, lambda img: _foreground(_centre(img, 0.3, 0.6, 0.5 * VIEWPORT["width"])).mean()
                             > 0.9, timeout=120)
            if page.get_by_text("Software WebGL rendering detected").count():  # SwiftShader's warning card
                page.locator("button.mantine-Notification-closeButton").first.click()
                time.sleep(0.5)
                shot = page.screenshot()
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            (ARTIFACTS / "viewer.png").write_bytes(shot)
            # the first keyframe's frustum and image lie in the middle of the initial view: off for the comparison
            page.get_by_label("keyframes", exact=True).uncheck()
            shot = _wait_for(page, lambda im: not np.allclose(_canvas_pixels(shot), im), timeout=20)
            img = _canvas_pixels(shot)
            # the map's colours: the project's render from the same viewpoint and field of view (the canvas is
            # VIEWPORT["height"] pixels over the keyframe's vertical field of view, centred at half the width)
            render = scene.frames.render(0, scene.initial_pose).astype(np.float32) / 255
            view = _centre(img, 0.3, 0.5, 0.5 * VIEWPORT["width"])
            expect = _centre(render, 0.3, 0.5)
            fg = _foreground(view)
            assert fg.mean() > 0.9
            diff = np.abs(view[fg].mean(axis=0) - expect.reshape(-1, 3).mean(axis=0))
            assert diff.max() < 0.08, (view[fg].mean(axis=0), expect.reshape(-1, 3).mean(axis=0))

            page.get_by_label("Gaussian map", exact=True).uncheck()
            off = _wait_for(page, lambda im: _foreground(_centre(im, 0.3, 0.5, 0.5 * VIEWPORT["width"])).mean()
                            < 0.5, timeout=30)
            assert not page.get_by_label("Gaussian map", exact=True).is_checked()
            assert scene.show["Gaussian map"].value is False
            (ARTIFACTS / "viewer_map_off.png").write_bytes(off)
            view_off = _centre(_canvas_pixels(off), 0.3, 0.5, 0.5 * VIEWPORT["width"])
            assert np.abs(view_off - view).mean() > 0.1
            browser.close()
    finally:
        server.stop()


def _wait_for(page, ok, timeout: float) -> bytes:
    """Screenshots until ``ok(canvas pixels)`` holds; the last one either way (the asserts that follow judge it)."""
    end = time.time() + timeout
    while True:
        shot = page.screenshot()
        if ok(_canvas_pixels(shot)) or time.time() > end:
            return shot
        time.sleep(1.0)


def test_run_view_serves_live_then_the_folder_until_ctrl_c(tmp_path):
    """``ggfslam run --view``: one address line first, the run's table, then it keeps serving the finished folder
    until Ctrl-C, which ends it with status 0 and leaves a complete run folder."""
    import signal
    import subprocess
    import sys
    import urllib.request

    config = Path(__file__).parents[1] / "configs" / "synthetic" / "default.yaml"
    cmd = [sys.executable, "-m", "ggfslam.cli", "run", str(config), "--out", str(tmp_path / "run"), "--view",
           "--port", "0", "--no-progress", "--set", "dataset.synthetic.n_frames=10",
           "--set", "dataset.synthetic.width=160", "--set", "dataset.synthetic.height=120",
           "--set", "mapping.iterations_per_keyframe=10", "--set", "mapping.final_iterations=10"]
    env = {**os.environ, "GGFSLAM_CACHE": str(tmp_path / "cache"), "COLUMNS": "200"}
    # Ctrl-C as in a terminal: a pytest started in the background (`&`, nohup) would hand the run SIGINT ignored
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("live viewer: http://localhost:"):
                port = int(line.split("localhost:")[1].split()[0])
                with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30) as page:  # the page is served
                    assert page.status == 200 and b"<html" in page.read(2000).lower()
            if "the viewer shows its folder until Ctrl-C" in line:
                break
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(lines) + out
    assert proc.returncode == 0, text[-3000:]
    assert lines[0].startswith("live viewer: http://localhost:") and "viewer stopped" in out
    assert json.loads((tmp_path / "run" / "run.json").read_text())["status"] == "finished"
    assert (tmp_path / "run" / "gaussians.ply").is_file() and (tmp_path / "run" / "metrics.json").is_file()
