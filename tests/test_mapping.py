"""Mapping loop: PSNR rises while training, pose corrections move the map, bounded keyframe cache,
the concurrent worker, losses, and checkpoint -> resume giving the same renders as an uninterrupted run."""
import json
import tempfile

import numpy as np
import pytest
import torch

from ggfslam import slam
from ggfslam.config import MappingConfig, config_from_dict
from ggfslam.data import sources
from ggfslam.data.types import Camera
from ggfslam.errors import ConfigError
from ggfslam.eval.image import depth_l1_cm, psnr
from ggfslam.gaussians.anchor_map import voxel_keys
from ggfslam.mapping.keyframe_store import KeyframeStore, resize_rgbd, scaled_intrinsics
from ggfslam.mapping.losses import depth_loss, normal_loss, opacity_entropy, photometric_loss
from ggfslam.mapping.mapper import Mapper
from ggfslam.mapping.worker import MappingWorker
from ggfslam.render.types import RenderSettings
from ggfslam.saved_run import load_mapper


def _mapper(ds, poses, **kw):
    cfg = MappingConfig(train_width=160, **kw)
    return Mapper(cfg, ds.camera, RenderSettings(backend="cpu"), lambda: dict(poses), tempfile.mkdtemp())


def test_psnr_and_depth_improve_while_mapping(sequence):
    ds, gt = sequence, sequence.gt_poses
    poses = {}
    m = _mapper(ds, poses)
    before, after = [], []
    for kf, fi in enumerate((0, 12, 24)):
        f = ds[fi]
        poses[kf] = gt[fi]
        assert m.add_keyframe(kf, fi, f.rgb, f.depth) > 0
        item = m.store.get(kf)
        out = m.render(gt[fi], exposure_kf=kf)
        before.append((psnr(out.color.numpy(), item.rgb), depth_l1_cm(out.depth.numpy(), item.depth)))
        m.train(40, focus=kf)
        out = m.render(gt[fi], exposure_kf=kf)
        after.append((psnr(out.color.numpy(), item.rgb), depth_l1_cm(out.depth.numpy(), item.depth)))
    for (p0, d0), (p1, d1) in zip(before, after):
        assert p1 > p0 + 3.0, (p0, p1)
        assert d1 < d0, (d0, d1)
    assert after[-1][0] > 24.0
    # a frame between keyframes (never trained on) is rendered well from its pose too
    f = ds[6]
    out = m.render(gt[6], exposure_kf=0)
    rgb, _ = resize_rgbd(f.rgb, f.depth, m.intr)
    assert psnr(out.color.numpy(), rgb) > 20.0
    st = m.stats()
    assert st["iterations"] == 120 and st["keyframes"] == 3 and st["gaussians"] > st["anchors"]


def test_vignetting_is_learned_into_the_camera_not_the_map(sequence):
    """Images darkened towards the corners by a known radial gain: the mapper learns that gain (shared by the
    keyframes), so the renders that carry it fit the images better than a map without it, and the map's own
    colours (renders without an exposure, the bake) stay the scene's."""
    from ggfslam.render.plane_depth import pixel_rays

    ds, gt = sequence, sequence.gt_poses
    cam = ds.camera
    rays = pixel_rays(scaled_intrinsics(cam, cam.width)).numpy()
    r2 = rays[..., 0] ** 2 + rays[..., 1] ** 2  # [H, W]
    true_gain = 1.0 - 0.6 * r2
    results = {}
    for on in (False, True):
        poses = {}
        m = _mapper(ds, poses, vignetting=on, lr_vignetting=0.02)  # fast enough for 120 steps
        for kf, fi in enumerate((0, 12, 24)):
            f = ds[fi]
            poses[kf] = gt[fi]
            m.add_keyframe(kf, fi, (f.rgb * true_gain[..., None]).astype(np.float32), f.depth)
            m.train(40, focus=kf)
        m.train(120)
        scores = [psnr(m.render(gt[fi], exposure_kf=kf).color.numpy(), m.store.get(kf).rgb)
                  for kf, fi in enumerate((0, 12, 24))]
        results[on] = (float(np.mean(scores)), m)
    (p_off, _), (p_on, m) = results[False], results[True]
    assert p_on > p_off + 0.3, (p_off, p_on)
    intr = m.intr
    r2s = pixel_rays(intr).numpy()
    r2s = r2s[..., 0] ** 2 + r2s[..., 1] ** 2
    learned = m.vignetting_gain(intr).detach().numpy()
    truth = 1.0 - 0.6 * r2s  # 0.66 in the corners
    # within 0.08 everywhere of a darkening that reaches 0.34 (the map's colours and the keyframes' exposures can
    # take a little of it: the split between r^2 and r^4 differs run to run, the gain itself little)
    assert np.abs(learned - truth).max() < 0.08, m.vignette
    # a render without an exposure is the map's own colour: brighter than the vignetted sensor image in the corners
    raw = m.render(gt[0]).color.numpy()
    vig = m.render(gt[0], exposure_kf=0).color.numpy()
    corner = r2s > 0.8 * r2s.max()
    assert raw[corner].mean() > vig[corner].mean() * 1.1
    # the camera's gain survives a checkpoint; an old checkpoint without it loads with none
    m2 = _mapper(ds, {k: gt[f] for k, f in enumerate((0, 12, 24))}, vignetting=True)
    st = m.state()
    m2.load_state(st)
    torch.testing.assert_close(m2.vignette.detach(), m.vignette.detach())
    del st["vignette"]
    for i in st["opt"]["param_groups"][-1]["params"]:
        st["opt"]["state"].pop(i, None)
    st["opt"]["param_groups"] = st["opt"]["param_groups"][:-1]
    m2.load_state(st)
    assert float(m2.vignette.detach().abs().sum()) == 0.0


@pytest.mark.parametrize("gauge", ["mean", "first"])
def test_a_keyframes_exposure_is_solved_not_learned(sequence, gauge):
    """A keyframe recorded darker and with an offset (0.7 x + 0.08): its solved exposure takes that change
    relative to the first keyframe's, and fits its image better than Adam's few small steps; the gauge holds (the
    first keyframe's exposure the identity, or all exposures' mean zero); the fit itself is the least-squares
    affine map from the vignetted render to the image, exactly."""
    ds, gt = sequence, sequence.gt_poses
    a_true, b_true = 0.7, 0.08
    results = {}
    for solved in (True, False):
        poses = {}
        m = _mapper(ds, poses, exposure_closed_form=solved, exposure_gauge=gauge)
        for kf, fi in enumerate((0, 12)):
            f = ds[fi]
            poses[kf] = gt[fi]
            rgb = f.rgb if kf == 0 else np.clip(a_true * f.rgb + b_true, 0, 1).astype(np.float32)
            m.add_keyframe(kf, fi, rgb, f.depth)
            m.train(40, focus=kf)
        m.train(40)
        if solved and gauge == "first":
            assert m.refit_exposures() == 1  # the first keyframe's exposure stays the identity
            assert float(m.exposure.detach()[m.exposure_row[0]].abs().max()) == 0.0
        elif solved:
            # after every step's fit the exposures are recentred: the map holds the keyframes' mean brightness
            assert float(m.exposure.detach().mean(dim=0).abs().max()) < 1e-6
            assert m.refit_exposures() == 2  # the final refit is each keyframe's own best fit, not recentred
            assert float(m.exposure.detach().mean(dim=0).abs().max()) < 0.02
        results[solved] = (psnr(m.render(gt[12], exposure_kf=1).color.numpy(), m.store.get(1).rgb), m)
    (p_solved, m), (p_adam, _) = results[True], results[False]
    assert p_solved > p_adam + 0.5, (p_solved, p_adam)
    e = m.exposure.detach()
    gain0, gain1 = e[m.exposure_row[0], :3].exp(), e[m.exposure_row[1], :3].exp()
    off0, off1 = e[m.exposure_row[0], 3:], e[m.exposure_row[1], 3:]
    np.testing.assert_allclose((gain1 / gain0).numpy(), a_true, atol=0.05)
    np.testing.assert_allclose((off1 - a_true * off0).numpy(), b_true, atol=0.03)
    # exact on an image made from the render itself with the camera's vignetting and a known affine map
    with torch.no_grad():
        m.vignette.copy_(torch.tensor([-0.3, 0.1]))
        out = m.render(gt[12])
        vignetted = m._vignetted(out.color, m.intr)  # what the camera records (the fit vignettes the render itself)
    a, b = torch.tensor([0.8, 1.1, 0.9]), torch.tensor([0.05, -0.02, 0.0])
    image = (vignetted * a + b).numpy()
    assert m._fit_exposure(1, out.color, out.alpha, image, m.intr, recentre=False)
    torch.testing.assert_close(m.exposure.detach()[m.exposure_row[1]], torch.cat([a.log(), b]), atol=1e-4, rtol=0)
    assert not m._fit_exposure(1, out.color, torch.zeros_like(out.alpha), image, m.intr)
    assert m._fit_exposure(0, out.color, out.alpha, image, m.intr) == (gauge == "mean")



@pytest.mark.parametrize("vignetting, exposure", [(True, True), (True, False), (False, True), (False, False)])
def test_sensor_model_matches_vignetting_then_exposure_in_torch(vignetting, exposure):
    """The compiled camera model against the mapper's torch chain (colour times 1 + v1 r2 + v2 r2^2, then
    exp(a) c + b): values and gradients of the image, the vignetting and the exposure, float32 and float64
    (gradcheck); the parameter sums do not depend on the thread count."""
    import numba

    from ggfslam.mapping.sensor_kernels import sensor_model

    g = torch.Generator().manual_seed(5)
    for dt, tol in ((torch.float32, 2e-5), (torch.float64, 1e-12)):
        color = torch.rand(23, 31, 3, generator=g, dtype=dt)
        r2 = torch.rand(23, 31, generator=g, dtype=dt) if vignetting else None
        v = torch.tensor([-0.3, 0.1], dtype=dt) if vignetting else None
        e = torch.tensor([0.1, -0.2, 0.05, 0.02, -0.01, 0.03], dtype=dt) if exposure else None
        gy = torch.randn(23, 31, 3, generator=g, dtype=dt)

        def reference(c, v, e):
            x = c * (1.0 + v[0] * r2 + v[1] * r2 * r2)[..., None] if v is not None else c
            return x * torch.exp(e[:3]) + e[3:] if e is not None else x

        leaves = [t.clone().requires_grad_() for t in (color, v, e) if t is not None]
        it = iter(leaves)
        c1, v1, e1 = next(it), (next(it) if vignetting else None), (next(it) if exposure else None)
        want = reference(c1, v1, e1)
        g_want = torch.autograd.grad(want, leaves, gy)
        leaves2 = [t.clone().requires_grad_() for t in leaves]
        it = iter(leaves2)
        c2, v2, e2 = next(it), (next(it) if vignetting else None), (next(it) if exposure else None)
        got = sensor_model(c2, r2, v2, e2)
        assert got.dtype == dt
        torch.testing.assert_close(got, want, rtol=tol, atol=tol)
        g_got = torch.autograd.grad(got, leaves2, gy)
        for a, b in zip(g_got, g_want):
            torch.testing.assert_close(a, b, rtol=tol * 10, atol=tol * 10)
        if dt == torch.float64:
            assert torch.autograd.gradcheck(lambda *xs: sensor_model(xs[0], r2, *(
                [xs[1]] if vignetting else [None]), *([xs[-1]] if exposure else [None])), tuple(leaves2))
            threads = numba.get_num_threads()
            try:
                numba.set_num_threads(1)
                g_one = torch.autograd.grad(sensor_model(c2, r2, v2, e2), leaves2, gy)
            finally:
                numba.set_num_threads(threads)
            assert all(torch.equal(a, b) for a, b in zip(g_one, g_got))
    with pytest.raises(ValueError, match="r2 and vignette"):
        sensor_model(color, None, torch.zeros(2), None)


def test_covered_moments_are_the_masked_sums():
    """The exposure fit's compiled statistics equal numpy's float64 sums over the covered pixels, whatever the
    thread count; mismatched shapes are refused with their shapes named."""
    import numba

    from ggfslam.mapping.exposure_kernels import covered_moments

    rng = np.random.default_rng(3)
    x, y = rng.random((37, 53, 3), dtype=np.float32), rng.random((37, 53, 3), dtype=np.float32)
    alpha = rng.random((37, 53), dtype=np.float32)
    m = alpha > 0.4
    xd, yd = x[m].astype(np.float64), y[m].astype(np.float64)
    want = np.stack([xd.sum(0), yd.sum(0), (xd * yd).sum(0), (xd * xd).sum(0)])
    n, sums = covered_moments(x, y, alpha, 0.4)
    assert n == m.sum()
    np.testing.assert_allclose(sums, want, rtol=1e-12)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        assert np.array_equal(covered_moments(x, y, alpha, 0.4)[1], sums)
    finally:
        numba.set_num_threads(threads)
    with pytest.raises(ValueError, match=r"\(37, 53\)"):
        covered_moments(x, y[:, :50], alpha, 0.4)
    # with the vignetting gain formed inside: the sums of the image vignetted in torch, to the bit
    r2 = rng.random((37, 53), dtype=np.float32)
    v = torch.tensor([-0.3, 0.07])
    xt, r2t = torch.from_numpy(x), torch.from_numpy(r2)
    vig = (xt * (1.0 + v[0] * r2t + v[1] * r2t * r2t)[..., None]).numpy()
    assert np.array_equal(covered_moments(x, y, alpha, 0.4, r2, tuple(v.tolist()))[1],
                          covered_moments(vig, y, alpha, 0.4)[1])


def _two_keyframes(ds) -> tuple[Mapper, dict]:
    """A mapper seeded (not trained) with frames 0 and 12 as keyframes 0 and 1 at their true poses."""
    gt = ds.gt_poses
    poses = {0: gt[0].copy(), 1: gt[12].copy()}
    m = _mapper(ds, poses)
    for kf, fi in enumerate((0, 12)):
        f = ds[fi]
        m.add_keyframe(kf, fi, f.rgb, f.depth)
    return m, poses


def test_backend_pose_corrections_move_the_keyframes_anchors(sequence):
    m, poses = _two_keyframes(sequence)
    own0 = m.map.source_kf == 0
    a0 = m.map.anchors.clone()
    n_before = m.map.n_anchors
    D = np.eye(4)
    D[:3, 3] = [0.05, 0.0, -0.02]  # a loop closure moves keyframe 0 by 5 cm
    poses[0] = D @ poses[0]
    assert m.sync_poses() == 1
    # every anchor left is one that was there, keyframe 0's moved with it, keyframe 1's where they were
    for kf, expected in ((0, a0[own0] + torch.tensor([0.05, 0.0, -0.02])), (1, a0[~own0])):
        now = m.map.anchors[m.map.source_kf == kf]
        assert len(now) > 0.5 * len(expected)
        gap = torch.cdist(now, expected, compute_mode="donot_use_mm_for_euclid_dist").min(dim=1).values
        assert float(gap.max()) < 1e-5
    # keyframe 0's anchors now overlap keyframe 1's (the two frames see the same walls): one per voxel is kept
    keys = voxel_keys(m.map.anchors.numpy().astype(np.float64), m.map.voxel_size)
    assert len(np.unique(keys)) == len(keys)
    assert m.merged == n_before - m.map.n_anchors > 0
    assert m.stats()["anchors_merged"] == m.merged
    assert m.sync_poses() == 0  # nothing moved since
    np.testing.assert_allclose(m.anchor_poses[0], poses[0])
    # seeding a keyframe again (a resumed run re-queuing it) neither adds anchors nor forgets where they sit
    n, placed = m.map.n_anchors, m.anchor_poses[1].copy()
    poses[1] = D @ poses[1]
    assert m.seed_keyframe(1) == 0 and m.map.n_anchors == n
    np.testing.assert_allclose(m.anchor_poses[1], placed)
    assert m.sync_poses() == 1


def test_render_without_the_anchors_a_keyframe_seeded(sequence):
    m, poses = _two_keyframes(sequence)
    full = m.render(poses[1]).alpha  # [H, W]
    torch.testing.assert_close(m.render(poses[1], without_kf=7).alpha, full)  # keyframe 7 seeded nothing
    for kf in (0, 1):
        part = m.render(poses[1], without_kf=kf).alpha
        assert (part <= full + 1e-5).all() and part.sum() < 0.99 * full.sum()


def test_the_map_covers_the_last_frame(tmp_path):
    """The input's last frame becomes a keyframe (``tracking.final_keyframe_after``): 11 frames after the last timed
    keyframe the orbit has turned far enough that, without it, a sixth of the last frame's surface is not in the map."""
    from ggfslam.geometry.se3 import pose_from_tum

    def run(after: int) -> tuple[float, dict, str]:
        cfg = config_from_dict({
            "name": "final-kf", "dataset": {"kind": "synthetic", "synthetic": {"n_frames": 36, "width": 320,
                                                                                "height": 240}},
            "tracking": {"keyframe_max_frames": 12, "final_keyframe_after": after, "virtual_baseline": 0.5},
            "mapping": {"iterations_per_keyframe": 20, "iterations_per_frame": 0, "final_iterations": 30,
                        "mesh": False, "train_width": 160, "eval_width": 160}}, "t")
        out = tmp_path / f"after{after}"
        metrics = slam.run(cfg, out, progress=False)
        _, mapper, _ = load_mapper(out)
        f = sources.open_dataset_from_config(cfg.dataset)[35]
        render = mapper.render(pose_from_tum(np.loadtxt(out / "trajectory.txt")[-1, 1:]))
        _, depth = resize_rgbd(f.rgb, f.depth, mapper.intr)
        covered = float((render.alpha.numpy()[depth > 0] > 0.5).mean())  # of the surface the sensor saw
        return covered, metrics["rendering"], (out / "tracking.txt").read_text().splitlines()[-1]

    covered, rendering, last_row = run(2)
    assert covered > 0.98, covered
    assert last_row.split()[:4] == ["35", last_row.split()[1], "ok", "1"], last_row  # tracking.txt marks it
    covered_off, rendering_off, last_row_off = run(0)
    assert covered_off < 0.9 and last_row_off.split()[3] == "0", (covered_off, last_row_off)
    # the sequence's depth error (all frames) falls with it: empty regions count their whole depth
    assert rendering["depth_l1_cm"] < 0.5 * rendering_off["depth_l1_cm"], (rendering, rendering_off)


def test_frames_at_rest_make_no_keyframes_but_keep_their_mapping_steps(tmp_path):
    """A camera resting at the end of the input (``tracking.keyframe_still_translation``): its frames make no
    keyframes, counted in metrics.json, and still earn their steps (``mapping.iterations_per_frame``), on the keyframe
    they rest at: the run trains exactly as many steps as with a keyframe every ``keyframe_max_frames`` frames."""
    from ggfslam.data.synthetic import SyntheticSequence
    from ggfslam.data.types import Frame
    from ggfslam.data.writer import write_tum_sequence

    seq = SyntheticSequence(n_frames=15, width=320, height=240, trajectory="orbit", seed=3)
    src = list(seq)
    rng = np.random.default_rng(0)
    frames = [Frame(i, i / 30.0, src[i].rgb if i < 15 else
                    np.clip(src[14].rgb + rng.normal(0, 0.004, src[14].rgb.shape), 0, 1).astype(np.float32),
                    src[min(i, 14)].depth, src[min(i, 14)].T_wc) for i in range(35)]  # at rest from frame 14
    folder = write_tum_sequence(tmp_path / "resting", frames, seq.camera)

    def run(gate: float) -> dict:
        cfg = config_from_dict({
            "name": "rest", "dataset": {"kind": "tum", "path": str(folder)},
            "tracking": {"keyframe_max_frames": 10, "keyframe_still_translation": gate},
            "mapping": {"iterations_per_keyframe": 1, "iterations_per_frame": 1.0, "final_iterations": 5,
                        "mesh": False, "train_width": 160, "eval_width": 160}}, "t")
        return slam.run(cfg, tmp_path / f"run{gate}", progress=False)

    held, every = run(0.005), run(0.0)
    assert every["tracking"]["frames_held_still"] == 0
    # due by time at 30-34, all at frame 20's keyframe (the first due at rest), whose steps they get as they come;
    # the last frame is held back too
    assert held["tracking"]["frames_held_still"] == 5
    assert held["mapping"]["keyframes"] == every["mapping"]["keyframes"] - 2  # 30 and 34 (the last frame)
    assert held["mapping"]["iterations"] == every["mapping"]["iterations"] == 35 + 5
    assert held["trajectory"]["ate_rmse_cm"] < 1.0


def test_frames_at_rest_are_paid_once_and_the_next_keyframe_gets_the_rest():
    """``Mapper.rest_steps`` and ``keyframe_budget`` share the frames between a keyframe and the next: those at rest
    are paid as they come (cumulative rounding, so 1.5 steps a frame stay 1.5 on average), the next keyframe gets
    the others, and together they make what one keyframe after all of them would have had."""
    from types import SimpleNamespace

    frames = {0: 0, 1: 20}  # keyframe id -> frame index
    store = SimpleNamespace(ids=lambda: sorted(frames), frame_index=lambda k: frames[k])
    m = SimpleNamespace(cfg=MappingConfig(iterations_per_keyframe=1, iterations_per_frame=1.5), store=store,
                        rest_paid_until=-1)
    assert Mapper.keyframe_budget(m, 1) == 30  # nothing at rest: 20 frames
    paid = [Mapper.rest_steps(m, f) for f in (30, 31, 32, 32)]  # 32 asked twice: paid once
    assert paid == [15, 1, 2, 0] and m.rest_paid_until == 32
    frames[2] = 40
    assert Mapper.keyframe_budget(m, 2) == 12  # frames 33-40
    assert sum(paid) + 12 == round(1.5 * 20)


def test_keyframe_store_is_bounded_and_reads_back_from_disk(tmp_path):
    cam = Camera(100.0, 100.0, 31.5, 23.5, 64, 48)
    intr = scaled_intrinsics(cam, 32)
    store = KeyframeStore(tmp_path / "kf", intr, cache_size=2)
    rng = np.random.default_rng(0)
    imgs = [(rng.uniform(0, 1, (48, 64, 3)).astype(np.float32), rng.uniform(0.5, 2, (48, 64)).astype(np.float32))
            for _ in range(5)]
    first = [store.add(i, 10 * i, *imgs[i]) for i in range(5)]
    assert store.cached == 2 and len(store) == 5 and len(list((tmp_path / "kf").glob("kf_*.npz"))) == 5
    back = store.get(0)  # evicted: read from disk
    np.testing.assert_allclose(back.rgb, first[0].rgb)
    np.testing.assert_array_equal(back.depth, first[0].depth)
    assert back.rgb.shape == (24, 32, 3) and back.frame_index == 0 and store.cached == 2
    again = KeyframeStore(tmp_path / "kf", intr, cache_size=2)  # a resumed run finds them
    assert again.ids() == [0, 1, 2, 3, 4] and again.frame_index(3) == 30


def test_scaled_intrinsics_keep_projections_consistent():
    cam = Camera(525.0, 520.0, 319.5, 239.5, 640, 480)
    s = scaled_intrinsics(cam, 320)
    assert (s.width, s.height) == (320, 240)
    X = np.array([0.3, -0.2, 2.0])
    u_full = cam.fx * X[0] / X[2] + cam.cx
    u_half = s.fx * X[0] / X[2] + s.cx
    assert u_half == pytest.approx((u_full + 0.5) * 0.5 - 0.5)
    assert scaled_intrinsics(cam, 1000).width == 640  # never upscaled


def test_losses_on_hand_made_inputs():
    img = torch.rand(32, 32, 3)
    assert float(photometric_loss(img, img)) == pytest.approx(0.0, abs=1e-6)
    assert float(photometric_loss(img + 0.1, img, lambda_ssim=0.0)) == pytest.approx(0.1, abs=1e-6)
    gt = torch.full((4, 4), 2.0)
    gt[0] = 0.0  # invalid sensor depth is ignored
    pred = torch.full((4, 4), 2.5)
    pred[0] = 100.0
    assert float(depth_loss(pred, gt)) == pytest.approx(0.5)
    n = torch.zeros(4, 4, 3)
    n[..., 2] = -1.0
    assert float(normal_loss(n, n)) == pytest.approx(0.0)
    tilted = n.clone()
    tilted[..., 0], tilted[..., 2] = np.sin(0.5), -np.cos(0.5)
    assert float(normal_loss(tilted, n)) == pytest.approx(1 - np.cos(0.5), abs=1e-6)


def test_opacity_entropy_value_and_gradient():
    o = torch.tensor([0.5, 0.1, 0.9, 0.999], dtype=torch.float64, requires_grad=True)
    h = [-(p * np.log(p) + (1 - p) * np.log(1 - p)) for p in (0.5, 0.1, 0.9, 0.999)]
    assert float(opacity_entropy(o.detach())) == pytest.approx(np.mean(h), rel=1e-12)
    assert float(opacity_entropy(torch.tensor([0.0, 1.0]))) == pytest.approx(0.0, abs=1e-4)  # clamped, finite
    opacity_entropy(o).backward()
    # d/do = ln((1 - o) / o) / n: zero at 0.5, pushing each opacity away from it
    np.testing.assert_allclose(o.grad.numpy(), [np.log((1 - p) / p) / 4 for p in (0.5, 0.1, 0.9, 0.999)], rtol=1e-9,
                               atol=1e-12)
    assert torch.autograd.gradcheck(opacity_entropy, (o.detach().clone().requires_grad_(True),))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_pointwise_terms_match_their_torch_references(dtype):
    """The compiled depth L1, opacity entropy and mean volume (pointwise_losses.py) against the plain-torch forms:
    values and gradients, ties and clamped ends included; finite differences in float64."""
    from ggfslam.mapping.losses import (depth_loss_reference, opacity_entropy_reference, scale_volume,
                                        scale_volume_reference)

    g = torch.Generator().manual_seed(0)
    tol = dict(rtol=1e-5, atol=1e-7) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-14)
    gt = (1.0 + torch.rand(37, 53, generator=g, dtype=dtype)) * (torch.rand(37, 53, generator=g) > 0.2)
    pred = gt + 0.1 * torch.randn(37, 53, generator=g, dtype=dtype)
    pred[3, :7] = gt[3, :7]  # ties: |.|'s gradient is 0 there
    o = torch.rand(5000, generator=g, dtype=dtype)
    o[:3] = torch.tensor([0.0, 1.0, 0.5], dtype=dtype)  # clamped ends, and the entropy's flat point
    s = 0.01 + torch.rand(5000, 3, generator=g, dtype=dtype)
    for fused, ref, x, extra in ((depth_loss, depth_loss_reference, pred, (gt,)),
                                 (opacity_entropy, opacity_entropy_reference, o, ()),
                                 (scale_volume, scale_volume_reference, s, ())):
        a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
        va, vb = fused(a, *extra), ref(b, *extra)
        assert va.dtype == dtype
        torch.testing.assert_close(va, vb, **tol)
        (3.0 * va).backward()
        (3.0 * vb).backward()
        torch.testing.assert_close(a.grad, b.grad, **tol)
        if dtype == torch.float64:
            small = x[:40].clone().requires_grad_() if x.dim() == 1 else None
            args = (small,) if small is not None else (x.clone().requires_grad_(),)
            if fused is depth_loss:  # away from the ties (|.| has a kink there)
                args = ((gt + 0.1 * torch.randn(37, 53, generator=g, dtype=dtype)).requires_grad_(),)
            if fused is opacity_entropy:  # inside the clamp
                args = ((0.05 + 0.9 * torch.rand(40, generator=g, dtype=dtype)).requires_grad_(),)
            assert torch.autograd.gradcheck(lambda t: fused(t, *extra), args)
    assert float(depth_loss(torch.ones(3, 3), torch.zeros(3, 3))) == 0.0  # no valid pixel: 0, not NaN


def test_keyframe_budget_follows_the_frames_between_keyframes(tmp_path, sequence):
    m = _mapper(sequence, {}, iterations_per_keyframe=7, iterations_per_frame=2.5)
    f = sequence[0]
    for kf, fi in enumerate((0, 2, 12)):
        m.store.add(kf, fi, f.rgb, f.depth)
    assert [m.keyframe_budget(k) for k in (0, 1, 2)] == [7, 7, 25]  # at least 7; 2.5 per frame since the last


def test_keyframe_errors_come_from_whole_images_at_one_size(sequence):
    """``_by_error`` compares keyframes by their last photometric loss, so it is taken at one size only and on
    whole images: the training size, or half of it where the training-size steps are crops."""
    gt, f = sequence.gt_poses, sequence[0]
    for kw, level in (({"coarse_fraction": 0.3, "crop": 0.5}, 1), ({"coarse_fraction": 0.85}, 0)):
        m = _mapper(sequence, {0: gt[0]}, coarse_min_width=64, **kw)
        m.add_keyframe(0, 0, f.rgb, f.depth)
        assert m.error_level == level
        m.step(0, 0, (0, 0, 80, 60))  # a crop never counts
        assert 0 not in m.kf_loss
        m.step(0, 1 - level)  # nor the other size
        assert 0 not in m.kf_loss
        m.step(0, level)
        assert m.kf_loss[0] == m.last_losses["photo"] > 0


def test_compiled_normal_loss_matches_the_torch_chain():
    """normal_loss_from_depth == normal_loss(normals_from_depth(depth)) in value and gradient, holes included."""
    from ggfslam.mapping.loss_kernels import normal_loss_from_depth
    from ggfslam.render.normals import normals_from_depth
    from ggfslam.render.types import Intrinsics

    g = torch.Generator().manual_seed(0)
    intr = Intrinsics(40.0, 42.0, 15.3, 11.7, 32, 24)
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    depth = (2.0 + 0.02 * u - 0.03 * v + 0.01 * torch.rand(24, 32, generator=g)).double()
    depth[5:8, 10:13] = 0.0  # a hole
    depth[15:, 20:] += 0.4  # a step
    sensor = (2.0 + 0.02 * u - 0.01 * v).double()
    sensor[0:3] = 0.0
    gt = normals_from_depth(sensor, intr.fx, intr.fy, intr.cx, intr.cy)
    a = depth.clone().requires_grad_()
    ref = normal_loss(normals_from_depth(a, intr.fx, intr.fy, intr.cx, intr.cy), gt)
    ref.backward()
    b = depth.clone().requires_grad_()
    fused = normal_loss_from_depth(b, gt, intr)
    fused.backward()
    assert float(ref.detach()) > 0.01
    torch.testing.assert_close(fused, ref, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(b.grad, a.grad, atol=1e-12, rtol=1e-9)


def test_compiled_photometric_loss_matches_the_torch_reference():
    """photometric_loss (compiled L1 + SSIM) == photometric_loss_reference in value and gradient, in float64 on an
    odd-sized image, and to float32 rounding at the training dtype."""
    from ggfslam.mapping.losses import photometric_loss, photometric_loss_reference

    g = torch.Generator().manual_seed(1)
    gt = torch.rand(23, 31, 3, generator=g, dtype=torch.float64)
    pred0 = (gt + 0.2 * torch.randn(23, 31, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    pred0[4:9, 6:12] = gt[4:9, 6:12]  # exact pixels: the L1 sign is 0 there in both
    for dtype, tol in ((torch.float64, 1e-10), (torch.float32, 2e-5)):
        a = pred0.to(dtype).clone().requires_grad_()
        ref = photometric_loss_reference(a, gt.to(dtype), 0.2)
        ref.backward()
        b = pred0.to(dtype).clone().requires_grad_()
        fused = photometric_loss(b, gt.to(dtype), 0.2)
        fused.backward()
        assert float(ref.detach()) > 0.05
        torch.testing.assert_close(fused, ref, atol=tol, rtol=tol)
        torch.testing.assert_close(b.grad, a.grad, atol=tol * 1e-2, rtol=tol * 10)
    # the reference itself against finite differences (the compiled loss is then right by the parity above)
    x = pred0[:12, :14].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p: photometric_loss(p, gt[:12, :14], 0.2), (x,), eps=1e-6, atol=1e-6)


def test_concurrent_worker_trains_every_keyframe(sequence):
    ds, gt = sequence, sequence.gt_poses
    poses = {}
    m = _mapper(ds, poses, iterations_per_keyframe=5, iterations_per_frame=0.1, idle_training=False)
    threads = torch.get_num_threads()
    w = MappingWorker(m, concurrent=True, threads=1)
    assert torch.get_num_threads() == 1  # tracking's share while both run
    for kf, fi in enumerate((0, 10, 20)):
        poses[kf] = gt[fi]
        f = ds[fi]
        w.submit(kf, fi, f.rgb, f.depth)
    w.finish()
    assert m.store.ids() == [0, 1, 2] and sorted(m.anchor_poses) == [0, 1, 2]
    assert m.iteration == 15 and w.pending() == {}
    assert torch.get_num_threads() == threads  # the final refinement gets the cores back


def test_a_realtime_worker_stores_off_the_caller_and_only_seeds_what_waits_at_the_end(sequence):
    ds, gt = sequence, sequence.gt_poses
    poses = {}
    m = _mapper(ds, poses, iterations_per_keyframe=400, idle_training=False)
    w = MappingWorker(m, concurrent=True, threads=1, realtime=True)
    for kf, fi in enumerate((0, 10, 20)):
        poses[kf] = gt[fi]
        f = ds[fi]
        w.submit(kf, fi, f.rgb, f.depth)
    pending = w.pending()  # a checkpoint now: every queued keyframe's images are in the store
    assert set(m.store.ids()) == {0, 1, 2} and set(pending) <= {0, 1, 2}
    w.finish()  # at once: the focused training in progress is cut short, what still waits is only seeded
    assert sorted(m.anchor_poses) == [0, 1, 2] and w.pending() == {}
    assert m.iteration < 400  # far from one keyframe's 400 focused steps, let alone three


def test_mapping_needs_the_orb_tracker():
    with pytest.raises(ConfigError, match="mapping.enabled"):
        config_from_dict({"dataset": {"kind": "synthetic"}, "tracking": {"method": "o3d_odometry"}}, "t")


def _resume_config(concurrent: bool = False):
    return config_from_dict({
        "dataset": {"kind": "synthetic", "synthetic": {"n_frames": 24, "width": 320, "height": 240}},
        "tracking": {"keyframe_max_frames": 5},
        "mapping": {"iterations_per_keyframe": 5, "final_iterations": 5, "checkpoint_every": 2, "mesh": False,
                    "eval_stride": 6, "train_width": 160, "concurrent": concurrent}}, "t")


def _interrupt_at_frame(monkeypatch, frame: int) -> None:
    """Make ``slam.run``'s dataset raise KeyboardInterrupt (as Ctrl-C would) when it reaches ``frame``."""
    real_open = sources.open_dataset_from_config

    def interrupted(c):
        ds = real_open(c)
        cls = ds.__class__

        class Stops(cls):
            def __getitem__(self, i):
                if i == frame:
                    raise KeyboardInterrupt
                return cls.__getitem__(self, i)

        ds.__class__ = Stops
        return ds

    monkeypatch.setattr(slam, "open_dataset_from_config", interrupted)


def test_resume_after_an_interruption_gives_the_same_run(tmp_path, monkeypatch):
    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    cfg = _resume_config()
    full = slam.run(cfg, tmp_path / "full", progress=False)

    _interrupt_at_frame(monkeypatch, 17)
    with pytest.raises(KeyboardInterrupt):
        slam.run(cfg, tmp_path / "cut", progress=False)
    assert json.loads((tmp_path / "cut" / "run.json").read_text())["status"] == "interrupted"
    monkeypatch.undo()
    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    resumed = slam.run(cfg, tmp_path / "cut", progress=False, resume=True)
    assert json.loads((tmp_path / "cut" / "run.json").read_text())["resumed_at_frame"] > 0
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "full" / "trajectory.txt"),
                                  np.loadtxt(tmp_path / "cut" / "trajectory.txt"))
    assert resumed["rendering"]["psnr"] == full["rendering"]["psnr"]
    assert resumed["mapping"]["anchors"] == full["mapping"]["anchors"]
    # and the saved maps render the same image
    _, ma, _ = load_mapper(tmp_path / "full")
    _, mb, _ = load_mapper(tmp_path / "cut")
    T = np.loadtxt(tmp_path / "full" / "keyframes.txt", ndmin=2)[1]
    from ggfslam.geometry.se3 import pose_from_tum

    pose = pose_from_tum(T[1:])
    torch.testing.assert_close(ma.render(pose).color, mb.render(pose).color, rtol=0, atol=0)


def test_concurrent_run_resumes_with_every_keyframe_seeded_once(tmp_path, monkeypatch):
    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    cfg = _resume_config(concurrent=True)
    _interrupt_at_frame(monkeypatch, 17)
    with pytest.raises(KeyboardInterrupt):
        slam.run(cfg, tmp_path / "cut", progress=False)
    monkeypatch.undo()
    monkeypatch.setenv("GGFSLAM_CACHE", str(tmp_path / "cache"))
    out = slam.run(cfg, tmp_path / "cut", progress=False, resume=True)
    assert json.loads((tmp_path / "cut" / "run.json").read_text())["status"] == "finished"
    _, m, _ = load_mapper(tmp_path / "cut")
    n_kf = len(np.loadtxt(tmp_path / "cut" / "keyframes.txt", ndmin=2))
    assert m.store.ids() == sorted(m.anchor_poses) == list(range(n_kf))
    # every keyframe got its steps and the final refinement ran (idle training may add more)
    assert out["mapping"]["iterations"] >= n_kf * cfg.mapping.iterations_per_keyframe + cfg.mapping.final_iterations


def test_abort_stops_the_worker_promptly(sequence):
    import time

    ds, gt = sequence, sequence.gt_poses
    poses = {0: gt[0]}
    m = _mapper(ds, poses, iterations_per_keyframe=10_000)
    w = MappingWorker(m, concurrent=True, threads=1)
    f = ds[0]
    w.submit(0, 0, f.rgb, f.depth)
    while m.iteration < 2:
        time.sleep(0.01)
    t0 = time.perf_counter()
    w.abort()
    assert time.perf_counter() - t0 < 5.0 and m.iteration < 10_000
