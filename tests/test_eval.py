"""Metrics against hand-computed values."""
import numpy as np
import pytest
import torch

from ggfslam.eval.image import (LPIPS, PSNR, SSIM, DepthL1, colour_error_split, depth_error_split, depth_l1_cm,
                                psnr, ssim, ssim_np)
from ggfslam.eval.perf import StageTimer, peak_rss_mb
from ggfslam.eval.report import metrics_table
from ggfslam.eval.trajectory import ATE, RPE, trajectory_metrics
from ggfslam.errors import ConfigError
from ggfslam.geometry.se3 import make_pose
from scipy.spatial.transform import Rotation


def poses_at(positions):
    return np.stack([make_pose(np.eye(3), p) for p in positions])


def test_ate_is_invariant_to_a_rigid_transform_of_the_estimate():
    rng = np.random.default_rng(0)
    gt = poses_at(np.cumsum(rng.normal(scale=0.1, size=(30, 3)), axis=0))
    G = make_pose(Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix(), [1, -2, 0.5])
    est = np.einsum("ij,njk->nik", G, gt)
    stamps = np.arange(30) * 0.1
    out = trajectory_metrics(stamps, est, stamps, gt)
    assert out["ate_rmse_cm"] < 1e-8 and out["rpe_trans_rmse_cm"] < 1e-8 and out["ate_pairs"] == 30


def test_ate_equals_hand_computed_offset():
    # symmetric layout: the optimal alignment is the identity, so every residual is exactly d
    d = 0.03
    gt_p = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=float)
    s = np.array([1, 1, -1, -1])
    est_p = gt_p + d * s[:, None] * np.array([0, 0, 1.0])
    stamps = np.arange(4, dtype=float)
    ate = ATE(max_diff=0.01)
    ate.process_data((stamps, poses_at(est_p), stamps, poses_at(gt_p)))
    assert ate.get_statistic("rmse") == pytest.approx(d, abs=1e-12)
    assert ate.get_statistic("max") == pytest.approx(d, abs=1e-12)
    np.testing.assert_allclose(ate.alignment, np.eye(4), atol=1e-12)


def test_ate_associates_by_timestamp_and_skips_unmatched():
    gt_p = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [5, 5, 5]], dtype=float)
    gt_t = np.array([0.0, 1.0, 2.0, 3.0, 10.0])
    est_t = np.array([0.005, 1.004, 1.999, 3.001])  # no estimate near t = 10
    ate = ATE(max_diff=0.01)
    ate.process_data((est_t, poses_at(gt_p[:4]), gt_t, poses_at(gt_p)))
    assert ate.num_pairs == 4 and ate.get_statistic("rmse") < 1e-12
    with pytest.raises(ValueError, match="associate"):
        ATE(max_diff=0.001).process_data((est_t + 100, poses_at(gt_p[:4]), gt_t, poses_at(gt_p)))


def test_rpe_of_a_constant_step_error():
    gt_p = np.array([[i, 0, 0] for i in range(10)], dtype=float)
    est_p = np.array([[1.1 * i, 0, 0] for i in range(10)], dtype=float)  # every step 10 cm too long
    t = np.arange(10, dtype=float)
    rpe = RPE(max_diff=0.01, delta=1)
    rpe.process_data((t, poses_at(est_p), t, poses_at(gt_p)))
    np.testing.assert_allclose(rpe.values, 0.1, atol=1e-12)


def test_psnr_ssim_depth_l1_hand_values():
    ref = np.full((16, 16, 3), 0.5, dtype=np.float32)
    img = ref + 0.1
    assert psnr(img, ref) == pytest.approx(20.0, abs=1e-4)
    assert psnr(ref, ref) == float("inf")
    mask = np.zeros((16, 16), bool)
    mask[:4] = True
    img2 = ref.copy()
    img2[4:] = 0.0  # errors only outside the mask
    assert psnr(img2, ref, mask) == float("inf")
    rng = np.random.default_rng(0)
    tex = rng.random((32, 32, 3)).astype(np.float32)
    assert ssim_np(tex, tex) == pytest.approx(1.0, abs=1e-6)
    assert ssim_np(tex, rng.random((32, 32, 3)).astype(np.float32)) < 0.2
    d_ref = np.array([[1.0, 2.0], [0.0, 4.0]])
    d = np.array([[1.01, 1.97], [9.0, 4.0]])
    assert depth_l1_cm(d, d_ref) == pytest.approx(100 * (0.01 + 0.03 + 0.0) / 3)


def test_ssim_is_differentiable():
    rng = np.random.default_rng(0)
    a = torch.tensor(rng.random((3, 24, 24)), dtype=torch.float32, requires_grad=True)
    b = torch.tensor(rng.random((3, 24, 24)), dtype=torch.float32)
    (1 - ssim(a, b)).backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


@pytest.mark.parametrize("shape", [(3, 24, 40), (2, 3, 31, 17), (3, 8, 8)])
def test_ssim_matches_pytorch_msssim_values_and_gradients(shape):
    from pytorch_msssim import ssim as reference

    g = torch.Generator().manual_seed(1)
    a = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    b = (a.detach() + 0.2 * torch.rand(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    ours = ssim(a, b)
    (ga,) = torch.autograd.grad(ours, a)
    a4 = a if a.dim() == 4 else a[None]
    ref = reference(a4, b if b.dim() == 4 else b[None], data_range=1.0, size_average=True)
    (gr,) = torch.autograd.grad(ref, a)
    # pytorch_msssim builds its window in float32 (ours is in the images' dtype): 1e-9-level differences
    assert ours.item() == pytest.approx(ref.item(), abs=1e-7)
    torch.testing.assert_close(ga, gr, rtol=1e-5, atol=1e-9)


@pytest.mark.parametrize("shape", [(480, 640), (37, 23), (11, 11), (8, 30)])
def test_ssim_np_is_the_differentiable_ssim(shape):
    """The evaluation's SSIM (OpenCV filters) gives the training loss's SSIM (torch, tested against pytorch_msssim
    above) to float32 precision, at a frame's size, odd sizes, the window's size and below it (the fallback)."""
    rng = np.random.default_rng(3)
    ref = rng.random(shape + (3,)).astype(np.float32)  # [H, W, 3]
    for img in (ref, np.clip(ref + rng.normal(0, 0.1, ref.shape), 0, 1).astype(np.float32),
                rng.random(shape + (3,)).astype(np.float32)):
        with torch.no_grad():
            want = float(ssim(torch.from_numpy(img).permute(2, 0, 1), torch.from_numpy(ref).permute(2, 0, 1)))
        assert ssim_np(img, ref) == pytest.approx(want, abs=1e-5)
    with pytest.raises(ValueError, match="RGB images"):
        ssim_np(ref[..., :2], ref[..., :2])


def test_rendered_normals_rule_is_the_compiled_one():
    """The evaluation scores a render's normals by the compiled rule (geometry/depth.py); the render's own
    ``normals`` (torch) must be the same rule, holes and borders included."""
    from ggfslam.geometry.depth import normals_from_depth as compiled
    from ggfslam.render.normals import normals_from_depth as rendered

    rng = np.random.default_rng(0)
    depth = (2.0 + 0.3 * rng.random((40, 50))).astype(np.float32)  # [H, W]
    depth[10:14, 20:25] = 0.0
    a = compiled(depth, 60.0, 58.0, 24.5, 19.5)
    b = rendered(torch.from_numpy(depth), 60.0, 58.0, 24.5, 19.5).numpy()
    np.testing.assert_array_equal(np.abs(a).sum(-1) == 0, np.abs(b).sum(-1) == 0)
    np.testing.assert_allclose(a, b, atol=2e-6)


def test_metric_interface_statistics():
    m = PSNR()
    ref = np.zeros((4, 4, 3), np.float32)
    m.process_data((ref + 0.1, ref))
    m.process_data((ref + 0.01, ref))
    assert m.get_statistic("mean") == pytest.approx(30.0, abs=1e-3)
    assert set(m.get_all_statistics()) >= {"rmse", "mean", "median", "max"}
    with pytest.raises(ValueError, match="unknown statistic"):
        m.get_statistic("p99")
    s, dl = SSIM(), DepthL1()
    s.process_data((ref, ref))
    dl.process_data((np.ones((2, 2)), np.full((2, 2), 1.5)))
    assert dl.get_statistic("mean") == pytest.approx(50.0)


def test_lpips_without_weights_reports_and_bad_weights_fail(tmp_path):
    assert not LPIPS(None).available
    bad = tmp_path / "lpips.pt"
    bad.write_text("not a model")
    with pytest.raises(ConfigError, match="lpips.pt"):
        LPIPS(bad)
    with pytest.raises(ConfigError, match="not found"):
        LPIPS(tmp_path / "missing.pt")


def test_lpips_with_a_local_torchscript_network(tmp_path):
    class L2(torch.nn.Module):
        def forward(self, x, y):
            return ((x - y) ** 2).mean()

    path = tmp_path / "net.pt"
    torch.jit.script(L2()).save(str(path))
    lp = LPIPS(path)
    a = np.zeros((8, 8, 3), np.float32)
    assert lp(a, a + 0.5) == pytest.approx(1.0)  # [-1, 1] scaling doubles the difference


def test_stage_timer_and_memory():
    t = StageTimer()
    for _ in range(3):
        with t("x"):
            sum(range(1000))
    s = t.summary()["x"]
    assert s["calls"] == 3 and s["fps"] > 0
    assert peak_rss_mb() > 10
    table = metrics_table({"trajectory": {"ate_rmse_cm": 1.234}, "tracking": {"frames": 3}})
    assert table.row_count == 2


def test_release_free_memory_returns_freed_heap_to_the_os():
    """With the renderer's allocator thresholds freed buffers stay in the process; the run's memory samples
    release them first, so they show what the run holds."""
    from ggfslam.eval.perf import current_rss_mb
    from ggfslam.render.cpu import release_free_memory, tune_allocator

    if not tune_allocator() and not release_free_memory():
        pytest.skip("not glibc, or its allocator settings are left to the environment")
    release_free_memory()
    base = current_rss_mb()
    block = np.ones(150 * 2**20 // 8)  # 150 MiB: under the raised mmap threshold, so it comes from the heap
    assert current_rss_mb() > base + 100
    del block
    held = current_rss_mb()
    assert release_free_memory()
    assert current_rss_mb() < held - 100


def test_depth_error_split_adds_up_to_the_l1():
    """A wall at 2 m with a box at 1 m: a blurred edge (the tail at a discontinuity), a hole, far noise."""
    ref = np.full((60, 80), 2.0)
    ref[20:40, 20:40] = 1.0
    ref[0, 0] = 0.0  # no sensor depth: not counted
    depth = ref.copy()
    depth[20:40, 19] = 1.5  # blended foreground/background beside the box's edge: 50 cm off
    depth[50, 60:70] = 0.0  # a hole: 2 m off
    depth[55, 70:75] += 0.08  # 8 cm off, away from any discontinuity
    depth[5:15, 5:15] += 0.01  # 1 cm off
    split = depth_error_split(depth, ref)
    n = (ref > 0).sum()
    assert split["depth_hole_cm"] == pytest.approx(100 * 10 * 2.0 / n)
    assert split["depth_tail_step_cm"] == pytest.approx(100 * 20 * 0.5 / n)
    assert split["depth_tail_cm"] == pytest.approx(100 * (20 * 0.5 + 5 * 0.08) / n)
    rest = 100 * 100 * 0.01 / n
    total = split["depth_hole_cm"] + split["depth_tail_cm"] + rest
    assert depth_l1_cm(depth, ref) == pytest.approx(total)
    assert split["depth_median_cm"] == 0.0


def test_colour_error_split_leaves_out_a_changing_screen_but_not_scattered_errors():
    """A 480x640 frame off by 0.02 everywhere, a 'screen' of 40x50 pixels showing something else (off by 0.6), and
    50 scattered pixels off by 0.6 (too small a region each to be left out)."""
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.2, 0.8, (480, 640, 3))
    img = ref + 0.02
    img[10:50, 500:550] = ref[10:50, 500:550] + 0.6  # 2000 px: above 0.13% of 307200 (400 px)
    ys, xs = rng.integers(100, 470, 50), rng.integers(0, 400, 50)
    img[ys, xs] = ref[ys, xs] - 0.6
    split = colour_error_split(img, ref)
    screen = np.zeros((480, 640), bool)
    screen[10:50, 500:550] = True
    assert split["gross_area_percent"] == pytest.approx(100 * 2000 / (480 * 640))
    assert split["psnr_without_gross"] == pytest.approx(psnr(img, ref, mask=~screen))
    assert split["psnr_without_gross"] > psnr(img, ref) + 5.0
    clean = colour_error_split(ref + 0.02, ref)  # nothing gross: the same figure as the PSNR
    assert clean["gross_area_percent"] == 0.0 and clean["psnr_without_gross"] == pytest.approx(psnr(ref + 0.02, ref))
