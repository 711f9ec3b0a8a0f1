"""CPU backend: the numba kernels of ``kernels_cpu`` wrapped in one ``torch.autograd.Function``.

One autograd node covers projection + rasterization (and the depth normalisation), so torch does no
per-Gaussian or per-pixel work: the forward returns colour [H, W, 3], raw depth, alpha, normalised depth
[H, W] and extras [H, W, K] as separate tensors;
the backward returns gradients for means, quats, scales, opacities, colours, extras, the world-to-camera
rotation and translation (float64; torch chains them to ``pose_xi``), the background, and a
"probe" [N, 2] whose gradient is dL/dmeans2d (the densification statistic; its value is not used).
Inputs are converted to contiguous float32 numpy arrays (no copy when already so).
"""
from __future__ import annotations

import ctypes
import os
import sys

import numba
import numpy as np
import torch

from ggfslam.render import kernels_cpu as kc
from ggfslam.render.types import Intrinsics, RenderSettings


class CpuRenderInfo:
    """Per-render byproducts filled by the forward pass (numpy arrays)."""

    radii: np.ndarray  # [N] int32
    visible: np.ndarray  # [N] bool
    means2d: np.ndarray  # [N, 2] float32
    depths: np.ndarray  # [N] float32
    n_pairs: int = 0  # (tile, Gaussian) pairs


_ALLOCATOR_TUNED: bool | None = None  # None: not tried yet; else whether the settings were applied


def tune_allocator() -> bool:
    """Keep freed memory in the process instead of returning it to the OS after every render.

    A render allocates ~15-30 MB of short-lived arrays (pair records, gradients). With glibc's defaults
    these come from fresh mmap'd pages each time: ~4000 page faults per render + backward, ~4 us each in
    this VM, i.e. 73 -> 58 ms at 320x240 and 140 -> 115 ms at 640x480 (100k Gaussians). This raises
    glibc's mmap threshold to 256 MB and its trim threshold to 512 MB (``mallopt``), process-wide.
    Called on the first CPU render unless ``GGFSLAM_MALLOC_TUNING=0``; the environment variables
    ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``, if set, take precedence (glibc reads them at
    start-up and we leave them alone). Tried once per process; returns whether the settings were applied."""
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED is not None:
        return _ALLOCATOR_TUNED
    _ALLOCATOR_TUNED = False
    if os.environ.get("GGFSLAM_MALLOC_TUNING", "1") == "0":
        return False
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    libc = _glibc()
    if libc is not None:
        m_trim_threshold, m_mmap_threshold = -1, -3
        ok = libc.mallopt(m_mmap_threshold, 256 << 20) == 1
        ok = (libc.mallopt(m_trim_threshold, 512 << 20) == 1) and ok
        _ALLOCATOR_TUNED = bool(ok)
    return _ALLOCATOR_TUNED


def release_free_memory() -> bool:
    """Return the heap's free pages to the OS (glibc ``malloc_trim``); returns whether it ran.

    With ``tune_allocator``'s thresholds glibc keeps up to 512 MB of freed render buffers, so RSS climbs to the
    largest render's high-water mark and stays there, whatever the run still holds. Called every few hundred
    frames (the run's memory samples), it keeps RSS near the live memory for the cost of one render's page
    faults (~16 ms). No-op off glibc."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True


def _glibc():
    """The C library when it is glibc (it has ``mallopt`` and ``malloc_trim``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except OSError:  # not glibc
        return None


PADDED_EXTRAS = 4
"""One to three extra channels are padded with zeros to four: the compiled rasterizer keeps exactly four extra
features in registers. Forward + backward at 600x340 with 146k Gaussians (Replica map, 2 threads): no extras
127 ms; one extra 167 ms through the general loop, 150 ms padded; four 205 -> 159 ms (2026-12-04)."""


def _np32(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(torch.float32).contiguous().numpy()


def _image_buffers(W: int, H: int, Kp: int, ntiles: int) -> tuple[np.ndarray, ...]:
    """``raster_forward``'s outputs: colour [H, W, 3], raw depth, extras [H, W, Kp], depth, final transmittance
    (float32), last contributor (int64), each tile's backward cost [ntiles] (float64)."""
    return (np.empty((H, W, 3), np.float32), np.empty((H, W), np.float32), np.empty((H, W, Kp), np.float32),
            np.empty((H, W), np.float32), np.empty((H, W), np.float32), np.empty((H, W), np.int64),
            np.empty(ntiles, np.float64))


def _gaussian_gradients(n: int, Kp: int, n_visible: int) -> tuple[np.ndarray, ...]:
    """``project_backward``'s outputs for n Gaussians: gradients of means, quaternions, scales, opacities, colours,
    extras and means2d (float32; it writes every row) and the pose gradient's partial sums per chunk of visible
    Gaussians [chunks, 12] (float64, zeroed)."""
    nchunks = max(1, (n_visible + kc.SOA_CHUNK - 1) // kc.SOA_CHUNK)
    return (np.empty((n, 3), np.float32), np.empty((n, 4), np.float32), np.empty((n, 3), np.float32),
            np.empty(n, np.float32), np.empty((n, 3), np.float32), np.empty((n, Kp), np.float32),
            np.empty((n, 2), np.float32), np.zeros((nchunks, 12), np.float64))


KERNEL_STAGES = ("composite_backward", "composite_forward", "projection")
"""The rasterizer's kernels in three groups, each compiled on its own (2026-12-07, fresh cache, one process: the
compositing's backward 13 s, its forward 11 s, projection + binning + the projection's backward 26 s)."""


def compile_kernels(stage: str) -> None:
    """Compile (or load from numba's cache) one group of ``KERNEL_STAGES`` with arguments of the types a render
    passes, running it on no Gaussians (or, for ``projection``, a few): each group compiles without the others, so
    processes can compile a fresh install's kernels side by side (``ggfslam/kernel_warmup.py``)."""
    W = H = kc.TILE  # one tile
    Kp = PADDED_EXTRAS
    C = 4 + Kp
    nworkers = max(1, numba.get_num_threads())
    bg = np.zeros(C, np.float64)
    srec, sfeat = np.empty((0, kc.REC), np.float32), np.empty((0, C), np.float32)
    pidx, tile_start, order = np.empty(0, np.int32), np.zeros(2, np.int64), np.zeros(1, np.int64)
    color, depth_raw, ext, depth, tfinal, last, work_bwd = _image_buffers(W, H, Kp, 1)
    if stage == "composite_forward":
        kc.raster_forward(srec, sfeat, pidx, tile_start, order, bg, W, H, 0.5, color, depth_raw, ext, depth, tfinal,
                          last, work_bwd, nworkers)
    elif stage == "composite_backward":
        tfinal[:] = 1.0
        last[:] = 0
        g_img = np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), np.zeros((H, W, Kp), np.float32)
        kc.raster_backward(srec, sfeat, pidx, tile_start, order, bg, W, H, 0.5, g_img[0], g_img[1], g_img[2],
                           g_img[1], g_img[1], depth_raw, tfinal, last, np.empty((0, kc.N_GEO + C), np.float32),
                           nworkers)
    elif stage == "projection":
        rng = np.random.default_rng(0)
        n = 8
        means = np.column_stack([rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(1.0, 2.0, n)]).astype(np.float32)
        quats = np.tile(np.float32([1, 0, 0, 0]), (n, 1))
        scales = np.full((n, 3), 0.05, np.float32)
        opac = np.full(n, 0.8, np.float32)
        colors, extras = np.full((n, 3), 0.5, np.float32), np.zeros((n, Kp), np.float32)
        R, t = np.eye(3), np.zeros(3)
        rec, radii, valid = np.empty((n, kc.REC), np.float32), np.empty(n, np.int32), np.empty(n, np.bool_)
        f = float(W)
        kc.project_forward(means, quats, scales, opac, R, t, f, f, W / 2, H / 2, W, H, 0.01, 100.0, 0.3, rec, radii,
                           valid, nworkers)
        vis, tile_start, pidx, srec, sfeat, pair_start, slot_pair, tile_cost = kc.bin_tiles(valid, rec, colors,
                                                                                            extras, W, H, nworkers)
        kc.tile_order(tile_cost)
        pg = np.zeros((pidx.shape[0], kc.N_GEO + C), np.float32)
        kc.project_backward(means, quats, scales, R, t, f, f, W / 2, H / 2, W, H, 0.3, vis, pair_start, slot_pair,
                            pg, *_gaussian_gradients(n, Kp, vis.shape[0]), nworkers)
    else:
        raise ValueError(f"compile_kernels: stage must be one of {', '.join(KERNEL_STAGES)}, got {stage!r}")


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, extras, R_cw, t_cw, probe, background,
                intr: Intrinsics, settings: RenderSettings, info: CpuRenderInfo):
        W, H = intr.width, intr.height
        n = means.shape[0]
        m_np, q_np, s_np, o_np, c_np = (_np32(means), _np32(quats), _np32(scales), _np32(opacities), _np32(colors))
        e_np = _np32(extras) if extras is not None else np.zeros((n, 0), np.float32)
        K = e_np.shape[1]
        Kp = PADDED_EXTRAS if 0 < K < PADDED_EXTRAS else K  # the kernels' fast path takes exactly four
        if Kp != K:
            e_np = np.ascontiguousarray(np.pad(e_np, ((0, 0), (0, Kp - K))))
        C = 4 + Kp
        R = R_cw.detach().to(torch.float64).contiguous().numpy()
        t = t_cw.detach().to(torch.float64).contiguous().numpy()
        rec = np.empty((n, kc.REC), np.float32)
        radii = np.empty(n, np.int32)
        valid = np.empty(n, np.bool_)
        nworkers = max(1, numba.get_num_threads())
        kc.project_forward(m_np, q_np, s_np, o_np, R, t, intr.fx, intr.fy, intr.cx, intr.cy, W, H,
                           float(settings.near_plane), float(settings.far_plane), float(settings.eps2d),
                           rec, radii, valid, nworkers)
        vis, tile_start, pidx, srec, sfeat, pair_start, slot_pair, tile_cost = kc.bin_tiles(valid, rec, c_np, e_np,
                                                                                            W, H, nworkers)
        bg = np.zeros(C, np.float64)
        bg[:3] = background.detach().to(torch.float64).numpy()
        color, depth_raw, ext, depth, tfinal, last, work_bwd = _image_buffers(W, H, Kp, tile_cost.shape[0])
        thr = float(settings.depth_min_alpha)
        kc.raster_forward(srec, sfeat, pidx, tile_start, kc.tile_order(tile_cost), bg, W, H, thr, color, depth_raw,
                          ext, depth, tfinal, last, work_bwd, nworkers)
        info.radii, info.visible = radii, valid
        info.means2d = rec[:, kc.R_MX:kc.R_MY + 1]
        info.depths = rec[:, kc.R_Z]
        info.n_pairs = int(pidx.shape[0])
        ctx.save_for_backward(means, quats, scales, R_cw, t_cw)
        ctx.np = (vis, tile_start, pidx, srec, sfeat, pair_start, slot_pair, bg, tfinal, last, work_bwd, K, Kp,
                  depth_raw)
        ctx.intr, ctx.settings, ctx.n = intr, settings, n
        alpha = 1.0 - tfinal
        return (torch.from_numpy(color), torch.from_numpy(depth_raw), torch.from_numpy(alpha),
                torch.from_numpy(depth), torch.from_numpy(np.ascontiguousarray(ext[..., :K]) if Kp != K else ext))

    @staticmethod
    def backward(ctx, g_color, g_depth_raw, g_alpha, g_depth, g_extras):
        if ctx.np is None:
            raise RuntimeError("the CPU rasterizer's backward ran twice on one render: its pair buffers are freed after "
                               "the first pass (retain_graph=True is not supported); render again for another gradient")
        means, quats, scales, R_cw, t_cw = ctx.saved_tensors
        (vis, tile_start, pidx, srec, sfeat, pair_start, slot_pair, bg, tfinal, last, work_bwd, K, Kp,
         depth_raw) = ctx.np
        intr, settings, n = ctx.intr, ctx.settings, ctx.n
        W, H = intr.width, intr.height
        C = 4 + Kp

        def g(t, shape):
            return np.zeros(shape, np.float32) if t is None else _np32(t)

        gc, gz, ga, gd = g(g_color, (H, W, 3)), g(g_depth_raw, (H, W)), g(g_alpha, (H, W)), g(g_depth, (H, W))
        ge = g(g_extras, (H, W, K))
        if Kp != K:
            ge = np.ascontiguousarray(np.pad(ge, ((0, 0), (0, 0), (0, Kp - K))))
        pg = np.empty((pidx.shape[0], kc.N_GEO + C), np.float32)
        nworkers = max(1, numba.get_num_threads())
        kc.raster_backward(srec, sfeat, pidx, tile_start, kc.tile_order(work_bwd), bg, W, H,
                           float(settings.depth_min_alpha), gc, gz, ge, gd, ga, depth_raw, tfinal, last, pg, nworkers)
        grads = _gaussian_gradients(n, Kp, vis.shape[0])
        g_means, g_quats, g_scales, g_opac, g_colors, g_extras, g_m2d, g_pose = grads
        R = R_cw.detach().to(torch.float64).contiguous().numpy()
        t = t_cw.detach().to(torch.float64).contiguous().numpy()
        kc.project_backward(_np32(means), _np32(quats), _np32(scales), R, t, intr.fx, intr.fy, intr.cx, intr.cy,
                            W, H, float(settings.eps2d), vis, pair_start, slot_pair, pg, g_means, g_quats, g_scales,
                            g_opac, g_colors, g_extras, g_m2d, g_pose, nworkers)
        gp = g_pose.sum(axis=0)
        need = ctx.needs_input_grad
        g_bg = None
        if need[9] and g_color is not None:
            g_bg = (g_color * torch.from_numpy(tfinal)[..., None].to(g_color.dtype)).sum(dim=(0, 1))
        ctx.np = None  # free the pair buffers as soon as possible
        return (
            torch.from_numpy(g_means) if need[0] else None,
            torch.from_numpy(g_quats) if need[1] else None,
            torch.from_numpy(g_scales) if need[2] else None,
            torch.from_numpy(g_opac) if need[3] else None,
            torch.from_numpy(g_colors) if need[4] else None,
            torch.from_numpy(np.ascontiguousarray(g_extras[:, :K])) if need[5] else None,
            torch.from_numpy(gp[:9].reshape(3, 3).copy()) if need[6] else None,
            torch.from_numpy(gp[9:].copy()) if need[7] else None,
            torch.from_numpy(g_m2d) if need[8] else None,
            g_bg,
            None, None, None,
        )


def rasterize_cpu(means, quats, scales, opacities, colors, extras, T_cw, intr: Intrinsics,
                  settings: RenderSettings, background: torch.Tensor, probe: torch.Tensor | None):
    """Render with the compiled kernels. ``T_cw`` [4, 4] float64 (may carry grad). Returns
    (color [H, W, 3], depth_raw [H, W], alpha [H, W], depth [H, W], extras [H, W, K], CpuRenderInfo)."""
    tune_allocator()
    info = CpuRenderInfo()
    R_cw = T_cw[:3, :3]
    t_cw = T_cw[:3, 3]
    color, depth_raw, alpha, depth, ext = _RasterizeCPU.apply(means, quats, scales, opacities, colors, extras, R_cw,
                                                              t_cw, probe, background, intr, settings, info)
    return color, depth_raw, alpha, depth, ext, info
