"""Compiled CPU kernels (numba) of the 3DGS rasterizer: projection, depth sort, tile binning, forward, backward.

Everything here works on numpy arrays; ``ggfslam.render.cpu`` wraps it in a ``torch.autograd.Function``.

Pipeline (one render)
1. ``project_forward`` (parallel over Gaussians): world -> camera, EWA 2D covariance with the ``eps2d``
   (0.3 px) blur, conic, pixel centre, view depth, 3-sigma radius and the *exact* pixel box where
   ``alpha = opacity * exp(power) >= 1/255`` (half-extents ``sqrt(2 ln(255 o) Sigma2_xx)``, ``..._yy``),
   clipped to the image. A conservative screen-space test (2D extent bounded by the largest scale)
   rejects off-screen Gaussians. Culled: depth outside [near, far], opacity < 1/255, non-finite values, empty
   box. Each Gaussian's result is one 64-byte float32 record. Computed in vector lanes, four Gaussians at once
   (see ``SOA_CHUNK``).
2. ``bin_tiles`` (every pass parallel over chunks of Gaussians or tile rows; serial only prefix sums): compaction,
   radix sort of the visible Gaussians by view depth (64-bit ``depth bits << 32 | index`` keys, digits counted
   per chunk), depth-ordered copies of their records and features (``srec``, ``sfeat``; a gather with software
   prefetch), per-tile lists (``TILE`` x ``TILE`` tiles, 32 x 32, depth order
   inside a tile) that hold each pair's depth rank (``pidx``, 4 bytes a pair). The rasterizers read a pair's record
   through ``pidx`` and prefetch the records of the pairs two steps ahead: the depth-ordered records are
   small (Nv x 64 bytes) and the prefetch hides most cache misses, so this is faster overall than copying a
   64+16-byte record per pair (measured, 100k Gaussians, render + backward: ~8 % faster at 320x240 and
   640x480; without the prefetch the indirect reads made the rasterizers ~30 % slower). Also: the pairs in
   Gaussian-major order (``slot_pair``: the backward writes per-pair gradients in pair order, and
   ``project_backward`` sums each Gaussian's through this list, with prefetch; no atomics. Writing them
   straight into Gaussian-major rows instead scattered ~40-byte writes over the whole array: ~20% of the
   backward at 320x240) and per-tile cost estimates.
3. Scheduling: every parallel kernel runs one ``prange`` iteration per worker thread, and the workers pull
   work items (tiles by decreasing estimated cost, rows, or chunks of Gaussians) from an atomic counter
   (``_fetch_add``). numba's OpenMP layer splits a ``prange`` statically; with another busy process on
   the two cores, static halves made a 2-thread render 3.5x slower than a 1-thread one. Results do not
   depend on the schedule (a tile is always handled by one worker; sums run in a fixed order).
4. ``raster_forward`` (parallel over tiles): front-to-back compositing. Each Gaussian visits only
   the pixels of its own box inside the tile; a pixel stops when its transmittance would fall below
   1e-4 (that Gaussian is not blended: the 3DGS rule); a tile stops when all its pixels have stopped.
   ``exp(power)`` comes from multiplicative recurrences (power is quadratic in x and y): libm ``exp``
   runs three times per (Gaussian, tile) pair, or twice per row in "chord" mode for very elongated,
   diagonal ellipses whose box corners would underflow. Channels ``[r, g, b, z, extras...]``; the
   background goes to the colour channels only. With no extras or exactly four (the caller pads one to
   three) a Gaussian's row in a tile is evaluated on 32, 16 or 8 pixels of the tile row at once, in vector
   lanes (``_blend_lanes``; see the comment above it): per lane, exp(power) moves from row to row by its
   own factor. Any other count of extras takes a scalar pixel loop (``_blend``;
   backward ``_unblend``, ``_unblend_grad``) with the recurrence along each row.
5. ``raster_backward`` (parallel over tiles): back to front over each pixel's contributors, with
   the same recurrences as the forward (bit-identical alphas), transmittance recovered by division by
   ``1 - alpha`` (alpha <= 0.99). Per pixel a single scalar ``R = dL/dC . (what lies behind) + T_final
   (bg . dL/dC - dL/dalpha_acc)`` carries everything behind. Per-pair gradient sums are written once per
   pair; the lane path keeps them per lane (sums over y, times 1, dy, dy^2) and sums over x at the pair's
   end, where dx is the lane's.
6. ``project_backward`` (parallel over visible Gaussians): sums its pairs, then the chain rule through
   conic -> 2D covariance -> (Jacobian, world-to-camera rotation, 3D covariance) -> quaternion, scales,
   and through the pixel centre and depth to the mean and the pose (dL/dR_cw, dL/dt_cw summed per chunk); the
   chain rule in vector lanes as the forward's projection.

Numerics: inputs float32; projection and compositing arithmetic in float64; records, images and
per-pair gradients stored as float32; fused multiply-add allowed (``fastmath={"contract"}``, ~5 %). The alpha
clamp at 0.99 has zero gradient where active (as torch's ``clamp``). Forward and backward kernels evaluate
alpha with identical code (shared inline helpers, pure products along the recurrences), so they agree on
every pixel's contributors.

numba caching: ``cache=True``; unless ``NUMBA_CACHE_DIR`` is set, the cache goes to
``~/.cache/ggfslam/numba`` (outside the repository). Threads: ``numba.set_num_threads`` is respected
(the caller's setting decides the number of workers).
"""
from __future__ import annotations

# numba's cache location, threading layer and OpenMP spinning (GOMP_SPINCOUNT): ggfslam/numba_setup.py, applied
# on package import. Measured before that setting (320x240, 100k Gaussians, render + backward, 2 threads): on an
# idle machine libgomp's default spinning was a little faster than GOMP_SPINCOUNT=10000 (medians 58 vs 63 ms);
# with another process busy on one of the two cores the default spinning starved the working thread (228 ms vs
# 97 ms with GOMP_SPINCOUNT=10000, and 128 ms with one thread).
import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.core.compiler import CompilerBase, DefaultPassBuilder
from numba.extending import intrinsic

FMA = {"contract"}  # the only fast-math flag used: fused multiply-add (no reassociation, NaN/Inf semantics kept)
TILE = 32  # tile side in pixels (see the comment above NPIX for why 32, not 16)
ALPHA_MIN = 1.0 / 255.0  # contributions below this alpha are skipped
ALPHA_MAX = 0.99  # alpha clamp
T_MIN = 1e-4  # a pixel stops before its transmittance would fall below this
BOX_REL_MARGIN = 1e-4  # the pixel box is enlarged a little; the kernels still test alpha exactly
BOX_ABS_MARGIN = 1e-3
Q_REL_MARGIN = 1e-4  # chord mode: q_max = 2 ln(255 o) (1 + 1e-4) + 1e-4
Q_ABS_MARGIN = 1e-4
SPAN_MARGIN = 1e-3  # chord mode: px added on both ends of a row span
CHORD_RHO2 = 0.96 ** 2  # squared correlation above which an ellipse uses chord mode
LOG255X2 = 2.0 * np.log(255.0)

CHUNK = 1024  # Gaussians per work item of the per-Gaussian kernels


class _WorkerPipeline(CompilerBase):
    """numba's nopython pipeline with array arguments marked ``noalias``: with ``error_model="numpy"`` on the
    decorator, the flags numba compiles a ``prange`` loop's body with. The compositing kernels' bodies are such
    workers, called once per thread from a two-line parallel wrapper (and the projection backward's chain rule is
    such a function), because numba's parfor passes (fusion, array analysis) over a large inlined loop body took
    most of their compile time: on the 2-core VM (2026-12-07) the forward compiled in 12.5 s instead of 28.7, the
    backward in 14.6 instead of 38.6; the outputs are the same to the bit and a training step as fast (forward 5-9%
    faster, backward 4-10% slower; 100k Gaussians, 320x240)."""

    def define_pipelines(self):
        self.state.flags.noalias = True
        return [DefaultPassBuilder.define_nopython_pipeline(self.state)]


@intrinsic
def _fetch_add(typingctx, counter, val):
    """Atomically ``old = counter[0]; counter[0] += val``; returns ``old`` (counter: 1-D int64 array).

    Used for dynamic scheduling: every worker of a ``prange`` over workers pulls the next work item, so a
    thread that the OS preempts (another process on the same 2 cores) does not hold back a static half of
    the work. (numba's OpenMP layer splits ``prange`` statically; measured under contention, static
    halves ran 3.5x slower than one thread.)"""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64):
        return None
    sig = types.int64(counter, types.int64)

    def codegen(context, builder, signature, args):
        arrty = signature.args[0]
        ary = context.make_array(arrty)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        ptr = cgutils.get_item_pointer(context, builder, arrty, ary, [zero], wraparound=False)
        return builder.atomic_rmw("add", ptr, args[1], "monotonic")

    return sig, codegen


def _prefetch_typer(arr, row, last_column: bool):
    """Signature and codegen of a software prefetch (read, keep in all cache levels) of ``arr[row, 0]`` or, with
    ``last_column``, ``arr[row, -1]`` (2-D C-contiguous array), or of ``arr[row]`` (1-D); None for other argument
    types."""
    if not (isinstance(arr, types.Array) and arr.ndim in (1, 2) and isinstance(row, types.Integer)):
        return None
    sig = types.void(arr, row)

    def codegen(context, builder, signature, args):
        arrty = signature.args[0]
        ary = context.make_array(arrty)(context, builder, args[0])
        r = context.cast(builder, args[1], signature.args[1], types.intp)
        if arrty.ndim == 1:
            idx = [r]
        elif last_column:
            idx = [r, builder.sub(cgutils.unpack_tuple(builder, ary.shape, 2)[1], context.get_constant(types.intp, 1))]
        else:
            idx = [r, context.get_constant(types.intp, 0)]
        ptr = cgutils.get_item_pointer(context, builder, arrty, ary, idx, wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def _prefetch(typingctx, arr, row):
    """Software prefetch of ``arr[row, 0]`` (2-D C-contiguous array) or ``arr[row]`` (1-D)."""
    return _prefetch_typer(arr, row, last_column=False)


@intrinsic
def _prefetch_last(typingctx, arr, row):
    """Software prefetch of ``arr[row, -1]`` (2-D C-contiguous array)."""
    return _prefetch_typer(arr, row, last_column=True)


PREFETCH_AHEAD = 8  # records prefetched ahead in gathers


@njit(cache=True, nogil=True, inline="always")
def _prefetch_pair(pk, pf, pidx, k, kend):
    """Prefetch the record and features of pair k (if k < kend; they may straddle two cache lines)."""
    if k < kend:
        j = pidx[k]
        _prefetch(pk, j)
        _prefetch_last(pk, j)
        _prefetch(pf, j)


# record of a projected Gaussian (float32 x 16)
R_MX, R_MY, R_CA, R_CB, R_CC, R_OP, R_QMAX, R_EA, R_EB, R_EC, R_CHORD, R_Z, R_X0, R_X1, R_Y0, R_Y1 = range(16)
REC = 16
# per-pair gradient record: d/d[mean_x, mean_y, conic_a, conic_b, conic_c, opacity, feat...]
N_GEO = 6


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _covariance3d(qw, qx, qy, qz, s0, s1, s2):
    """World covariance of a Gaussian with unit quaternion (w, x, y, z) and scales s: the rotation R (9 entries,
    row-major), M = R diag(s) (9) and Sigma = M M^T (S00, S01, S02, S11, S12, S22): 24 values."""
    r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    r01 = 2.0 * (qx * qy - qw * qz)
    r02 = 2.0 * (qx * qz + qw * qy)
    r10 = 2.0 * (qx * qy + qw * qz)
    r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    r12 = 2.0 * (qy * qz - qw * qx)
    r20 = 2.0 * (qx * qz - qw * qy)
    r21 = 2.0 * (qy * qz + qw * qx)
    r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    m00 = r00 * s0
    m01 = r01 * s1
    m02 = r02 * s2
    m10 = r10 * s0
    m11 = r11 * s1
    m12 = r12 * s2
    m20 = r20 * s0
    m21 = r21 * s1
    m22 = r22 * s2
    S00 = m00 * m00 + m01 * m01 + m02 * m02
    S01 = m00 * m10 + m01 * m11 + m02 * m12
    S02 = m00 * m20 + m01 * m21 + m02 * m22
    S11 = m10 * m10 + m11 * m11 + m12 * m12
    S12 = m10 * m20 + m11 * m21 + m12 * m22
    S22 = m20 * m20 + m21 * m21 + m22 * m22
    return (r00, r01, r02, r10, r11, r12, r20, r21, r22, m00, m01, m02, m10, m11, m12, m20, m21, m22,
            S00, S01, S02, S11, S12, S22)


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _covariance2d(S00, S01, S02, S11, S12, S22, Rt, fx, fy, z, rx, ry, rz, limxp, limxn, limyp, limyn, eps2d):
    """EWA projection of the world covariance Sigma at camera point (x, y, z) = z (rx, ry, 1), rz = 1 / z:
    the projection Jacobian J with the usual clamp of x/z, y/z (clamped tx, ty; j00, j02, j11, j12), T2 = J Rcw
    (a, 2x3 row-major), the rows of T2 Sigma (u, v) and Sigma2 = T2 Sigma T2^T + eps2d I as (ca, cb, cc):
    21 values."""
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = Rt
    tx = z * min(limxp, max(-limxn, rx))
    ty = z * min(limyp, max(-limyn, ry))
    j00 = fx * rz
    j02 = -fx * tx * rz * rz
    j11 = fy * rz
    j12 = -fy * ty * rz * rz
    a00 = j00 * R00 + j02 * R20
    a01 = j00 * R01 + j02 * R21
    a02 = j00 * R02 + j02 * R22
    a10 = j11 * R10 + j12 * R20
    a11 = j11 * R11 + j12 * R21
    a12 = j11 * R12 + j12 * R22
    u0 = S00 * a00 + S01 * a01 + S02 * a02
    u1 = S01 * a00 + S11 * a01 + S12 * a02
    u2 = S02 * a00 + S12 * a01 + S22 * a02
    v0 = S00 * a10 + S01 * a11 + S02 * a12
    v1 = S01 * a10 + S11 * a11 + S12 * a12
    v2 = S02 * a10 + S12 * a11 + S22 * a12
    ca = a00 * u0 + a01 * u1 + a02 * u2 + eps2d
    cb = a10 * u0 + a11 * u1 + a12 * u2
    cc = a10 * v0 + a11 * v1 + a12 * v2 + eps2d
    return (tx, ty, j00, j02, j11, j12, a00, a01, a02, a10, a11, a12, u0, u1, u2, v0, v1, v2, ca, cb, cc)


# Both projection kernels work on chunks of SOA_CHUNK Gaussians: a scalar pass gathers a chunk's inputs into the
# worker's buffer laid out field by field (structure of arrays at constant offsets, indices unsigned and masked
# into the chunk, so the compiler sees the fields disjoint), one branch-free loop over the chunk does the
# arithmetic and LLVM vectorises it (four Gaussians per AVX2 register: the long chains of divisions and square
# roots of one Gaussian no longer stall a scalar loop; culls become selects), and a scalar pass scatters the
# results (the forward adds the records' exponentials there, which do not vectorise; the backward adds the pose
# terms in Gaussian order). Outputs bit-identical to the scalar loops they replaced, except the pose gradient's
# rounding (1e-16 relative). Measured on a capture of bench_mapping.py's throughput scene (93k Gaussians, 82k
# visible, 148k pairs, 2 threads): forward 3.2 -> 2.0 ms, backward 4.4 -> 2.9 ms (docs/MEASUREMENTS.md).
SOA_CHUNK = 256  # Gaussians per work item (project_backward's caller sizes g_pose_chunks by it)
SOA_MASK = np.uint64(SOA_CHUNK - 1)
PF_IN = 12  # project_forward's buffer fields in: mean (3), quaternion (4), scales (3), opacity, ln(255 opacity)
PF_VALID = REC  # out: the 16 record fields (the three exponentials left 0), then valid (0 / 1) and the radius
PF_RADIUS = REC + 1
PF_OUT = REC + 2
PB_IN = 16  # project_backward's fields in: dL/d(mx, my, conic a, b, c, z), mean (3), quaternion (4), scales (3)
PB_OUT = 22  # out: dL/d mean (3), quaternion (4), scales (3), then the 12 pose terms (dL/dRcw row-major, dL/dtcw)


@njit(cache=True, nogil=True, inline="always")
def _field(f, jj):
    """Buffer index of field f of the chunk's Gaussian jj (unsigned and masked: no aliasing between fields)."""
    return np.uint64(f * SOA_CHUNK) + (np.uint64(jj) & SOA_MASK)


@njit(cache=True, nogil=True)  # not inlined into the callers' IR: numba's parfor array analysis fails on it there
def _view(Rcw, fx, fy, cx, cy, width, height):
    """The world-to-camera rotation as a 9-tuple (row-major) and the limits of x/z, y/z beyond which the EWA
    Jacobian is clamped (the image's extent plus 30% of the half field of view): (Rt, limxp, limxn, limyp, limyn)."""
    tanx = 0.5 * width / fx
    tany = 0.5 * height / fy
    limxp = (width - cx) / fx + 0.3 * tanx
    limxn = cx / fx + 0.3 * tanx
    limyp = (height - cy) / fy + 0.3 * tany
    limyn = cy / fy + 0.3 * tany
    Rt = (Rcw[0, 0], Rcw[0, 1], Rcw[0, 2], Rcw[1, 0], Rcw[1, 1], Rcw[1, 2], Rcw[2, 0], Rcw[2, 1], Rcw[2, 2])
    return Rt, limxp, limxn, limyp, limyn


@njit(cache=True, nogil=True, inline="always")
def _soa_gather_shape(buf, f, jj, means, quats, scales, i):
    """Gaussian i's mean, quaternion and scales into buffer fields f..f+9 of the chunk's Gaussian jj."""
    for c in range(3):
        buf[_field(f + c, jj)] = means[i, c]
    for c in range(4):
        buf[_field(f + 3 + c, jj)] = quats[i, c]
    for c in range(3):
        buf[_field(f + 7 + c, jj)] = scales[i, c]


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _soa_camera_point(buf, f, jj, Rt, t0, t1, t2):
    """Gaussian jj's mean from buffer fields f..f+2 (world) and in the camera: (pwx, pwy, pwz, x, y, z)."""
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = Rt
    pwx = buf[_field(f, jj)]
    pwy = buf[_field(f + 1, jj)]
    pwz = buf[_field(f + 2, jj)]
    x = R00 * pwx + R01 * pwy + R02 * pwz + t0
    y = R10 * pwx + R11 * pwy + R12 * pwz + t1
    z = R20 * pwx + R21 * pwy + R22 * pwz + t2
    return pwx, pwy, pwz, x, y, z


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _soa_unit_quaternion(buf, f, jj):
    """Gaussian jj's quaternion (w, x, y, z) from buffer fields f..f+3, normalised, with its norm as read and
    clamped at 1e-12: (qw, qx, qy, qz, norm, clamped norm)."""
    qw = buf[_field(f, jj)]
    qx = buf[_field(f + 1, jj)]
    qy = buf[_field(f + 2, jj)]
    qz = buf[_field(f + 3, jj)]
    qn_raw = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qn = max(qn_raw, 1e-12)
    return qw / qn, qx / qn, qy / qn, qz / qn, qn_raw, qn


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def project_forward(means, quats, scales, opac, Rcw, tcw, fx, fy, cx, cy, width, height, near, far, eps2d,
                    rec, radii, valid, nworkers):
    """Project N Gaussians. Outputs (preallocated): rec [N, 16] f32 (see R_* fields; conic (a, b, c) with
    power = -0.5 (a dx^2 + c dy^2) - b dx dy, dx = mean_x - u; box x0, x1, y0, y1 inclusive), radii [N] i32
    (3-sigma, px; 0 when culled), valid [N] bool. rec[:, R_Z] holds the view depth of every Gaussian
    (0 where not finite); other fields of culled Gaussians are 0. Per chunk of SOA_CHUNK Gaussians: gather (with
    ln(255 o)), the projection in vector lanes (``_project_lanes``), then the records with their exponentials."""
    n = means.shape[0]
    Rt, limxp, limxn, limyp, limyn = _view(Rcw, fx, fy, cx, cy, width, height)
    nchunks = (n + SOA_CHUNK - 1) // SOA_CHUNK
    counter = np.zeros(1, np.int64)
    for _w in prange(nworkers):
        buf = np.empty((PF_IN + PF_OUT) * SOA_CHUNK, np.float64)
        while True:
            ch = _fetch_add(counter, np.int64(1))
            if ch >= nchunks:
                break
            i0 = ch * SOA_CHUNK
            i1 = min(n, i0 + SOA_CHUNK)
            for i in range(i0, i1):
                jj = i - i0
                _soa_gather_shape(buf, 0, jj, means, quats, scales, i)
                o = np.float64(opac[i])
                buf[_field(10, jj)] = o
                buf[_field(11, jj)] = np.log(255.0 * o)
            _project_lanes(buf, np.uint64(i1 - i0), Rt, tcw[0], tcw[1], tcw[2], fx, fy, cx, cy, width, height, near,
                           far, eps2d, limxp, limxn, limyp, limyn)
            for i in range(i0, i1):
                jj = i - i0
                ok = buf[_field(PF_IN + PF_VALID, jj)] != 0.0
                valid[i] = ok
                radii[i] = np.int32(buf[_field(PF_IN + PF_RADIUS, jj)])
                for f in range(REC):
                    rec[i, f] = buf[_field(PF_IN + f, jj)]
                if ok:
                    rec[i, R_EA] = np.exp(-np.float64(rec[i, R_CA]))
                    rec[i, R_EB] = np.exp(-np.float64(rec[i, R_CB]))
                    rec[i, R_EC] = np.exp(-np.float64(rec[i, R_CC]))


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _project_lanes(buf, n, Rt, t0, t1, t2, fx, fy, cx, cy, width, height, near, far, eps2d, limxp, limxn, limyp,
                   limyn):
    """The projection of ``project_forward`` for the chunk's n Gaussians, branch-free: everything is computed for
    every Gaussian and the culls (depth outside [near, far], opacity < 1/255, off screen by a conservative bound,
    a degenerate 2D covariance, an empty pixel box) select zeros."""
    limx2 = max(limxp, limxn) ** 2
    limy2 = max(limyp, limyn) ** 2
    for jj in range(n):
        x, y, z = _soa_camera_point(buf, 0, jj, Rt, t0, t1, t2)[3:]
        o = buf[_field(10, jj)]
        s0 = buf[_field(7, jj)]
        s1 = buf[_field(8, jj)]
        s2 = buf[_field(9, jj)]
        rz = 1.0 / z
        rx = x * rz
        ry = y * rz
        mx = fx * rx + cx
        my = fy * ry + cy
        # conservative screen-space cull: Sigma2_xx <= |row0(J)|^2 max(s)^2 + eps2d, opacity <= 1
        smax2 = max(s0 * s0, max(s1 * s1, s2 * s2))
        bx = np.sqrt(LOG255X2 * ((fx * rz) ** 2 * (1.0 + limx2) * smax2 + eps2d)) * 1.01 + 1.0
        by = np.sqrt(LOG255X2 * ((fy * rz) ** 2 * (1.0 + limy2) * smax2 + eps2d)) * 1.01 + 1.0
        ok = (z >= near) & (z <= far) & (o >= ALPHA_MIN)
        ok &= (mx + bx >= 0.0) & (mx - bx <= width - 1.0) & (my + by >= 0.0) & (my - by <= height - 1.0)
        # 3D covariance from the unit quaternion (w, x, y, z) and the scales
        qw, qx, qy, qz = _soa_unit_quaternion(buf, 3, jj)[:4]
        S00, S01, S02, S11, S12, S22 = _covariance3d(qw, qx, qy, qz, s0, s1, s2)[18:]
        ca, cb, cc = _covariance2d(S00, S01, S02, S11, S12, S22, Rt, fx, fy, z, rx, ry, rz, limxp, limxn, limyp,
                                   limyn, eps2d)[18:]
        det = ca * cc - cb * cb
        ok &= (det > 0.0) & np.isfinite(det) & np.isfinite(mx) & np.isfinite(my)
        # exact box of alpha >= 1/255:  d^T Sigma2^-1 d <= 2 ln(255 o)
        k2 = 2.0 * buf[_field(11, jj)]
        ex = np.sqrt(k2 * ca) * (1.0 + BOX_REL_MARGIN) + BOX_ABS_MARGIN
        ey = np.sqrt(k2 * cc) * (1.0 + BOX_REL_MARGIN) + BOX_ABS_MARGIN
        fx0 = max(np.ceil(mx - ex), 0.0)
        fx1 = min(np.floor(mx + ex), width - 1.0)
        fy0 = max(np.ceil(my - ey), 0.0)
        fy1 = min(np.floor(my + ey), height - 1.0)
        ok &= (fx0 <= fx1) & (fy0 <= fy1)
        idet = 1.0 / det
        qa = np.float64(np.float32(cc * idet))  # the conic as the rasterizers will see it
        qb = np.float64(np.float32(-cb * idet))
        qc = np.float64(np.float32(ca * idet))
        mid = 0.5 * (ca + cc)
        lam = mid + np.sqrt(max(0.1, mid * mid - det))
        v = 1.0 if ok else 0.0
        buf[_field(PF_IN + PF_VALID, jj)] = v
        buf[_field(PF_IN + PF_RADIUS, jj)] = np.ceil(3.0 * np.sqrt(lam)) if ok else 0.0
        buf[_field(PF_IN + R_MX, jj)] = mx if ok else 0.0
        buf[_field(PF_IN + R_MY, jj)] = my if ok else 0.0
        buf[_field(PF_IN + R_CA, jj)] = qa if ok else 0.0
        buf[_field(PF_IN + R_CB, jj)] = qb if ok else 0.0
        buf[_field(PF_IN + R_CC, jj)] = qc if ok else 0.0
        buf[_field(PF_IN + R_OP, jj)] = o if ok else 0.0
        buf[_field(PF_IN + R_QMAX, jj)] = k2 * (1.0 + Q_REL_MARGIN) + Q_ABS_MARGIN if ok else 0.0
        buf[_field(PF_IN + R_EA, jj)] = 0.0
        buf[_field(PF_IN + R_EB, jj)] = 0.0
        buf[_field(PF_IN + R_EC, jj)] = 0.0
        # recurrence mode needs |correlation| <= 0.96: box corners then have power >= -q_max / 0.08
        buf[_field(PF_IN + R_CHORD, jj)] = 1.0 if ok and qb * qb > CHORD_RHO2 * qa * qc else 0.0
        buf[_field(PF_IN + R_Z, jj)] = z if np.isfinite(z) else 0.0
        buf[_field(PF_IN + R_X0, jj)] = fx0 if ok else 0.0
        buf[_field(PF_IN + R_X1, jj)] = fx1 if ok else 0.0
        buf[_field(PF_IN + R_Y0, jj)] = fy0 if ok else 0.0
        buf[_field(PF_IN + R_Y1, jj)] = fy1 if ok else 0.0


RADIX_CHUNK = 16384  # keys per work item of the radix sort's histogram and scatter passes


@njit(cache=True, nogil=True, parallel=True)
def _radix_sort_hi32(a, tmp, nworkers):
    """Stable sort of uint64 values by their upper 32 bits (LSD radix, three 11-bit digits; a pass whose digit
    is the same for every value is skipped). Each pass counts digits per chunk of keys and scatters the chunks in
    parallel, chunk c's keys of digit b after those of chunks < c: the order is the serial sort's. Returns the
    sorted array (``a`` or ``tmp``)."""
    n = a.shape[0]
    nch = max(1, (n + RADIX_CHUNK - 1) // RADIX_CHUNK)
    hist = np.empty((nch, 2048), np.int64)
    m = np.uint64(2047)
    for shift in (32, 43, 54):
        sh = np.uint64(shift)
        counter = np.zeros(1, np.int64)
        for _w in prange(nworkers):
            while True:
                ch = _fetch_add(counter, np.int64(1))
                if ch >= nch:
                    break
                hist[ch, :] = 0
                for j in range(ch * RADIX_CHUNK, min(n, (ch + 1) * RADIX_CHUNK)):
                    hist[ch, (a[j] >> sh) & m] += 1
        if n == 0:
            continue
        b0 = (a[0] >> sh) & m
        same = 0
        for ch in range(nch):
            same += hist[ch, b0]
        if same == n:
            continue
        tot = 0
        for b in range(2048):
            for ch in range(nch):
                c = hist[ch, b]
                hist[ch, b] = tot
                tot += c
        counter[0] = 0
        for _w in prange(nworkers):
            while True:
                ch = _fetch_add(counter, np.int64(1))
                if ch >= nch:
                    break
                for j in range(ch * RADIX_CHUNK, min(n, (ch + 1) * RADIX_CHUNK)):
                    v = a[j]
                    b = (v >> sh) & m
                    tmp[hist[ch, b]] = v
                    hist[ch, b] += 1
        a, tmp = tmp, a
    return a


@njit(cache=True, nogil=True, parallel=True)
def bin_tiles(valid, rec, colors, extras, width, height, nworkers):
    """Depth-sort the visible Gaussians and build the tile lists.

    Returns
      vis [Nv] i32: original index of each visible Gaussian (ascending index order, "compact" order);
      tile_start [ntiles+1] i64: pairs of tile t are tile_start[t]:tile_start[t+1], in depth order;
      pidx [npairs] i32: depth rank of the pair's Gaussian (its row in srec / sfeat);
      srec [Nv, 16] f32: records in depth order; sfeat [Nv, 4+K] f32: their (r, g, b, z, extras);
      pair_start [Nv+1] i64, slot_pair [npairs] i64: the pairs in Gaussian-major order: compact Gaussian j's
      are slot_pair[pair_start[j]:pair_start[j+1]] (the backward writes its per-pair gradients in pair order,
      ``project_backward`` sums each Gaussian's through this);
      tile_cost [ntiles] f64: estimated forward cost of each tile.
    Every pass is parallel over chunks of Gaussians or over tile rows; the serial parts are prefix sums over
    chunks, rows and tiles. The outputs do not depend on the number of workers."""
    n = valid.shape[0]
    K = extras.shape[1]
    C = 4 + K
    ntx = (width + TILE - 1) // TILE
    nty = (height + TILE - 1) // TILE
    ntiles = ntx * nty
    # compaction (index order): per chunk its visible Gaussians and pairs, then sort keys (depth bits << 32 |
    # compact index) and pair offsets
    nchi = max(1, (n + CHUNK - 1) // CHUNK)
    cvis = np.zeros(nchi + 1, np.int64)
    cpair = np.zeros(nchi + 1, np.int64)
    counter = np.zeros(1, np.int64)
    for _w in prange(nworkers):
        while True:
            ch = _fetch_add(counter, np.int64(1))
            if ch >= nchi:
                break
            c = 0
            tot = 0
            for i in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
                if valid[i]:
                    c += 1
                    tot += _pair_count(rec, i)
            cvis[ch + 1] = c
            cpair[ch + 1] = tot
    for ch in range(nchi):
        cvis[ch + 1] += cvis[ch]
        cpair[ch + 1] += cpair[ch]
    nv = cvis[nchi]
    vis = np.empty(nv, np.int32)
    skey = np.empty(nv, np.uint64)
    pair_start = np.empty(nv + 1, np.int64)
    pair_start[0] = 0
    zbits = rec.view(np.uint32)  # non-negative float32 depths sort like their bit patterns
    counter[0] = 0
    for _w in prange(nworkers):
        while True:
            ch = _fetch_add(counter, np.int64(1))
            if ch >= nchi:
                break
            j = cvis[ch]
            tot = cpair[ch]
            for i in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
                if valid[i]:
                    vis[j] = i
                    skey[j] = (np.uint64(zbits[i, R_Z]) << np.uint64(32)) | np.uint64(j)
                    tot += _pair_count(rec, i)
                    j += 1
                    pair_start[j] = tot
    skey = _radix_sort_hi32(skey, np.empty(nv, np.uint64), nworkers)  # stable: ties keep the compact order
    # depth-ordered copies (parallel gather; the rasterizers read the records from here), with per chunk the
    # number of Gaussians and of pairs in each tile row
    srec = np.empty((nv, REC), np.float32)
    sfeat = np.empty((nv, C), np.float32)
    str_ = np.empty((nv, 4), np.int32)  # tile ranges tx0, tx1, ty0, ty1
    sbase = np.empty(nv, np.int64)
    nch = max(1, (nv + CHUNK - 1) // CHUNK)
    rcount = np.zeros((nch, nty), np.int64)
    rpair = np.zeros((nch, nty), np.int64)
    counter[0] = 0
    for _w in prange(nworkers):
        while True:
            ch = _fetch_add(counter, np.int64(1))
            if ch >= nch:
                break
            s1 = min(nv, (ch + 1) * CHUNK)
            for s in range(ch * CHUNK, s1):
                if s + PREFETCH_AHEAD < s1:
                    ia = vis[np.int64(skey[s + PREFETCH_AHEAD] & np.uint64(0xFFFFFFFF))]
                    _prefetch(rec, ia)
                    _prefetch(colors, ia)
                    if K > 0:
                        _prefetch(extras, ia)
                jj = np.int64(skey[s] & np.uint64(0xFFFFFFFF))
                i = vis[jj]
                for f in range(REC):
                    srec[s, f] = rec[i, f]
                sfeat[s, 0] = colors[i, 0]
                sfeat[s, 1] = colors[i, 1]
                sfeat[s, 2] = colors[i, 2]
                sfeat[s, 3] = rec[i, R_Z]
                for c in range(K):
                    sfeat[s, 4 + c] = extras[i, c]
                tx0, tx1, ty0, ty1 = _tile_range(rec, i)
                str_[s, 0] = tx0
                str_[s, 1] = tx1
                str_[s, 2] = ty0
                str_[s, 3] = ty1
                sbase[s] = pair_start[jj]
                for r in range(ty0, ty1 + 1):
                    rcount[ch, r] += 1
                    rpair[ch, r] += tx1 - tx0 + 1
    # rows of tiles: depth-ordered lists of the Gaussians touching each row (chunk ch's after those of chunks
    # < ch) and where each row's pairs begin
    row_start = np.zeros(nty + 1, np.int64)
    row_pairs = np.zeros(nty + 1, np.int64)
    for r in range(nty):
        c = row_start[r]
        p = row_pairs[r]
        for ch in range(nch):
            k = rcount[ch, r]
            rcount[ch, r] = c
            c += k
            p += rpair[ch, r]
        row_start[r + 1] = c
        row_pairs[r + 1] = p
    row_list = np.empty(row_start[nty], np.int32)
    counter[0] = 0
    for _w in prange(nworkers):
        while True:
            ch = _fetch_add(counter, np.int64(1))
            if ch >= nch:
                break
            for s in range(ch * CHUNK, min(nv, (ch + 1) * CHUNK)):
                for r in range(str_[s, 2], str_[s, 3] + 1):
                    row_list[rcount[ch, r]] = s
                    rcount[ch, r] += 1
    npairs = row_pairs[nty]
    tile_start = np.empty(ntiles + 1, np.int64)
    tile_start[ntiles] = npairs
    pidx = np.empty(npairs, np.int32)
    slot_pair = np.empty(npairs, np.int64)
    tile_cost = np.empty(ntiles, np.float64)
    counter[0] = 0
    for _w in prange(nworkers):
        tile_area = np.empty(ntx, np.int64)  # pixels of the pairs' boxes per tile of the row
        cur = np.empty(ntx, np.int64)  # pairs per tile of the row, then each tile's next free position
        while True:
            r = _fetch_add(counter, np.int64(1))
            if r >= nty:
                break
            _fill_row(r, row_start, row_pairs, row_list, str_, srec, sbase, tile_start, cur, pidx, slot_pair,
                      tile_cost, tile_area, ntx, width, height)
    return vis, tile_start, pidx, srec, sfeat, pair_start, slot_pair, tile_cost


@njit(cache=True, nogil=True, inline="always")
def _tile_range(rec, i):
    """Tiles (tx0, tx1, ty0, ty1), inclusive, that Gaussian i's pixel box touches."""
    return (np.int64(rec[i, R_X0]) // TILE, np.int64(rec[i, R_X1]) // TILE, np.int64(rec[i, R_Y0]) // TILE,
            np.int64(rec[i, R_Y1]) // TILE)


@njit(cache=True, nogil=True, inline="always")
def _pair_count(rec, i):
    """Number of tiles that Gaussian i's pixel box touches."""
    tx0, tx1, ty0, ty1 = _tile_range(rec, i)
    return (tx1 - tx0 + 1) * (ty1 - ty0 + 1)


@njit(cache=True, nogil=True, inline="always")
def _fill_row(r, row_start, row_pairs, row_list, tr, crec, pair_start, tile_start, cur, pidx, slot_pair,
              tile_cost, tile_area, ntx, width, height):
    """Tile row r of ``bin_tiles``: its tiles' sizes and starts (the row's pairs begin at row_pairs[r]), then each
    Gaussian of the row appended to its tiles' pair lists. Here tr, crec and pair_start are in depth order and
    row_list holds depth ranks, so reads go forward in memory. cur and tile_area [ntx] are the worker's own: the
    per-pair counts and cursors in an array shared by the workers put neighbouring rows' tiles in one cache line
    (the pass took 3.3 ms on two threads against 1.9 ms on one)."""
    py0 = r * TILE
    py1 = min(py0 + TILE, height) - 1
    for t in range(ntx):
        cur[t] = 0
        tile_area[t] = 0
    qend = row_start[r + 1]
    for q in range(row_start[r], qend):
        j = row_list[q]
        hgt = min(np.int64(crec[j, R_Y1]), py1) - max(np.int64(crec[j, R_Y0]), py0) + 1
        bx0 = np.int64(crec[j, R_X0])
        bx1 = np.int64(crec[j, R_X1])
        for t in range(tr[j, 0], tr[j, 1] + 1):
            cur[t] += 1
            px0 = t * TILE
            tile_area[t] += (min(bx1, min(px0 + TILE, width) - 1) - max(bx0, px0) + 1) * hgt
    pos = row_pairs[r]
    for t in range(ntx):
        tile_start[r * ntx + t] = pos
        c = cur[t]
        cur[t] = pos
        pos += c
    for q in range(row_start[r], qend):
        if q + PREFETCH_AHEAD < qend:  # the slots are scattered (Gaussian-major order): fetch ahead
            _prefetch(slot_pair, pair_start[row_list[q + PREFETCH_AHEAD]])
        j = row_list[q]
        tx0 = tr[j, 0]
        nx = tr[j, 1] - tx0 + 1
        base = pair_start[j] + (r - tr[j, 2]) * nx - tx0
        for t in range(tx0, tr[j, 1] + 1):
            pos = cur[t]
            cur[t] = pos + 1
            pidx[pos] = j
            slot_pair[base + t] = pos
    # cost: 0.8 per pixel of each pair's box in the tile plus 8 per pair (the pixels summed as integers in the counting
    # pass: a float sum per pair in the fill pass was ~1 ms of bin_tiles' 5 at 100k Gaussians, this ~0.4)
    for t in range(ntx):
        tile = r * ntx + t
        tile_cost[tile] = 0.8 * tile_area[t] + 8.0 * (cur[t] - tile_start[tile])


@njit(cache=True, nogil=True)
def tile_order(cost):
    """Tiles by decreasing estimated cost: workers pull them in this order (longest first), which keeps the
    end of a parallel pass short."""
    return np.argsort(-cost)


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _row_span(mx, ca, cb, cc, qmax, dy, gx0, gx1):
    """Chord mode: pixels x of the row at offset dy (= mean_y - y) where d^T conic d <= qmax, clipped to
    [gx0, gx1]. Returns (x0, x1, G, E): G = exp(power) at x0, E = exp(power(x0 + 1) - power(x0))."""
    bdy = cb * dy
    disc = bdy * bdy - ca * (cc * dy * dy - qmax)
    if disc < 0.0:
        return np.int64(1), np.int64(0), 0.0, 0.0
    hw = np.sqrt(disc) / ca + SPAN_MARGIN
    xc = mx + bdy / ca
    x0 = max(gx0, np.int64(np.ceil(xc - hw)))
    x1 = min(gx1, np.int64(np.floor(xc + hw)))
    dx = mx - x0
    G = np.exp(-0.5 * ca * dx * dx - bdy * dx - 0.5 * cc * dy * dy)
    E = np.exp(ca * dx - 0.5 * ca + bdy)
    return x0, x1, G, E


@njit(cache=True, nogil=True, inline="always")
def _load_pair(pk, pf, j, x0, x1, y0, y1):
    """The record of sorted pair j (its pixel box clipped to the tile [x0, x1] x [y0, y1]) as float64 scalars:
    (gx0, gx1, gy0, gy1, mean x, mean y, conic a, b, c, opacity, qmax, ea, eb, ec, chord flag, f0..f3); the
    forward and backward rasterizers read pairs identically through this."""
    return (max(np.int64(pk[j, R_X0]), x0), min(np.int64(pk[j, R_X1]), x1),
            max(np.int64(pk[j, R_Y0]), y0), min(np.int64(pk[j, R_Y1]), y1),
            np.float64(pk[j, R_MX]), np.float64(pk[j, R_MY]),
            np.float64(pk[j, R_CA]), np.float64(pk[j, R_CB]), np.float64(pk[j, R_CC]),
            np.float64(pk[j, R_OP]), np.float64(pk[j, R_QMAX]),
            np.float64(pk[j, R_EA]), np.float64(pk[j, R_EB]), np.float64(pk[j, R_EC]),
            pk[j, R_CHORD] != 0.0,
            np.float64(pf[j, 0]), np.float64(pf[j, 1]), np.float64(pf[j, 2]), np.float64(pf[j, 3]))


@njit(cache=True, nogil=True, inline="always")
def _load_extras4(pf, j):
    """Features 4..7 of pair j as float64 scalars when there are exactly eight (four extras), else zeros."""
    if pf.shape[1] == 8:
        return np.float64(pf[j, 4]), np.float64(pf[j, 5]), np.float64(pf[j, 6]), np.float64(pf[j, 7])
    return 0.0, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _pair_start(mx, my, ca, cb, cc, gx0, gy0):
    """Recurrence mode: at pixel (gx0, gy0) returns G = exp(power), the x-step factor
    E = exp(power(x+1, y) - power(x, y)) and the y-step factor F = exp(power(x, y+1) - power(x, y))."""
    dx = mx - gx0
    dy = my - gy0
    G = np.exp(-0.5 * ca * dx * dx - cb * dx * dy - 0.5 * cc * dy * dy)
    E = np.exp(ca * dx - 0.5 * ca + cb * dy)
    F = np.exp(cb * dx + cc * dy - 0.5 * cc)
    return G, E, F


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _blend(T, Tstop, p, o, g):
    """Front-to-back step of a Gaussian (opacity o, exp(power) g) at pixel p: returns its blending weight
    alpha * T and updates T[p]; returns -1 when the pixel stops here instead (T would fall below T_MIN: this
    Gaussian is not blended, T[p] becomes 0 and Tstop[p] keeps the final transmittance)."""
    tp = T[p]
    alpha = min(ALPHA_MAX, o * g)
    alpha = alpha if alpha >= ALPHA_MIN else 0.0
    nt = tp * (1.0 - alpha)
    if nt < T_MIN and tp != 0.0:
        Tstop[p] = tp
        T[p] = 0.0
        return -1.0
    T[p] = nt
    return alpha * tp


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _unblend(T, p, ga):
    """Back-to-front step at pixel p of a Gaussian with unclamped alpha ga: (weight, transmittance in front of
    it, 1 / (1 - alpha)), the transmittance recovered from T[p] (behind it) by the same arithmetic as
    ``_blend``; weight -1 where ``_blend`` blended nothing (alpha below ALPHA_MIN)."""
    alpha = min(ALPHA_MAX, ga)
    if alpha < ALPHA_MIN:
        return -1.0, 0.0, 0.0
    iom = 1.0 / (1.0 - alpha)
    ti = T[p] * iom
    return alpha * ti, ti, iom


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _unblend_grad(T, Rr, p, fg, w, ti, iom, ga, dx, s0, s1, s2):
    """Finish ``_unblend``'s step given fg = features . dL/dpixel: moves T[p] and the pixel's remainder Rr[p] in
    front of the Gaussian and adds dL/dpower (times 1, dx, dx^2) to the row sums (s0, s1, s2), which it returns.
    The alpha clamp has zero gradient where active."""
    dlda = ti * fg - Rr[p] * iom
    Rr[p] += fg * w
    T[p] = ti
    if ga <= ALPHA_MAX:
        dpow = ga * dlda
        s0 += dpow
        t1 = dpow * dx
        s1 += t1
        s2 += t1 * dx
    return s0, s1, s2


# Vector lanes (the C = 4 and C = 8 channel paths of both rasterizers): a Gaussian's row inside a tile is evaluated
# on a window of lanes at once: the whole tile row (32 pixels), 16 where the Gaussian's box is at most 16 wide or 8
# where it is at most 8 (the window starts at its first pixel, or as far right as it fits; only the window's lanes are
# cleared for each pair). Lanes outside the box carry exp(power) = 0, the loops are
# branch-free, and LLVM vectorises them. Lane i's exp(power) moves to the next row by a per-lane factor (power is
# quadratic, so the factor is exp(power(x, y+1) - power(x, y)), itself geometric in x and multiplied by exp(-c) per
# row), set up once per (Gaussian, tile) pair by the multiplicative recurrences along the box's first row. A worker's
# whole tile state lives in one float64 buffer at the constant offsets below, and row starts and window offsets are
# masked into their ranges (planes padded by a row, lane arrays by half a row): then the compiler can prove the
# planes disjoint and vectorises without runtime alias checks. Measured on captured renders of fr3/cabinet (large
# Gaussians; old and new kernels alternating in one process): forward 68.6 -> 41.9 ms at 640x480, backward 81.6 ->
# 54.9 ms; on the small Gaussians of bench_mapping.py's throughput scene at 320x240 9.2 -> 8.0 and 13.2 -> 10.9 ms.
# Tiles of 32 instead of 16 pixels (2026-12-07): a Gaussian's box meets fewer tiles, so there are fewer (Gaussian,
# tile) pairs, each with its set-up (record loads, three exponentials, the first row's recurrences, the backward's
# per-pair sums); the third, 8-lane window keeps small Gaussians from paying for wider rows. Pairs of captured renders
# 357k -> 146k (fr3/cabinet, 640x480), 141k -> 75k (the same at 320x240), 141k -> 108k (the throughput scene);
# binning + forward + backward, two threads, kernels alternating in one process: 105.2 -> 99.0 ms, 32.7 -> 30.9 ms,
# 25.5 -> 22.9 ms. With 32-pixel tiles and only the two wider windows the throughput scene was 2.5% slower (its
# boxes are mostly at most 8 wide); with 16-pixel tiles and a 4-lane third window all were slower.
NPIX = TILE * TILE
ROW_MASK = np.uint64(NPIX - TILE)  # a row start inside the tile: 0, 32, ..., 992
WIN_MASK = np.uint64(TILE - 1)  # a window's offset: 0 (32 lanes), 0..16 (16), 0..24 (8); masked to 0..31
NLANE = TILE + TILE // 2  # lane arrays hold a masked offset (<= 31) plus a narrower window's lanes (<= 15)
PLANE = NPIX + TILE  # pixel planes hold a row start + masked window offset + lane <= 1038
L_G = np.uint64(0)  # [NLANE] the row's exp(power) per lane
L_F = np.uint64(NLANE)  # [NLANE] per lane, the factor to the next row's exp(power)
L_T = np.uint64(2 * NLANE)  # [PLANE] transmittance
L_S = L_T + np.uint64(PLANE)  # [PLANE] forward: transmittance at the stop; backward: the remainder R
L_L = L_T + np.uint64(2 * PLANE)  # [PLANE] last contributor (one past its pair index, as float64)
L_C = L_T + np.uint64(3 * PLANE)  # [8, PLANE] forward: accumulated channels; backward: dL/d(channel)
L_ACC = L_C + np.uint64(8 * PLANE)  # backward, per lane: [3, NLANE] dL/dpower sums (x 1, dy, dy^2), [8, NLANE] dL/dfeat
LANE_BUF = int(L_ACC) + 11 * NLANE


@njit(cache=True, nogil=True, inline="always")
def _lane(base, i):
    """Buffer index of lane or plane entry i (unsigned: no negative-index wrapping, which stops vectorisation)."""
    return base + np.uint64(i)


@njit(cache=True, nogil=True, inline="always")
def _plane(c, p):
    """Buffer index of pixel p (0..NPIX-1, or a lane's pixel) of channel plane c."""
    return L_C + np.uint64(c * PLANE) + np.uint64(p)


@njit(cache=True, nogil=True, inline="always")
def _window(gx0, gx1, x0):
    """(offset, width) of the lane window that covers the box columns [gx0, gx1] of the tile starting at x0: a
    quarter of the tile row (8 lanes), half of it (16) or all of it (32), the narrowest that holds the box."""
    if gx1 - gx0 < TILE // 4:
        return min(gx0 - x0, TILE - TILE // 4), TILE // 4
    if gx1 - gx0 < TILE // 2:
        return min(gx0 - x0, TILE // 2), TILE // 2
    return 0, TILE


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _lanes_start(tb, x0, gx0, gx1, ws, nw, G, E, F, ea, eb):
    """Lanes of the pair's first row: exp(power) G at pixel gx0 times the x-step factor E (itself times ea per
    pixel), and the row-step factor F at gx0 (times eb per pixel); zero in the rest of the window [ws, ws + nw)
    (lanes outside the window are not read)."""
    for i in range(ws, ws + nw):
        tb[_lane(L_G, i)] = 0.0
        tb[_lane(L_F, i)] = 0.0
    for x in range(gx0, gx1 + 1):
        tb[_lane(L_G, x - x0)] = G
        tb[_lane(L_F, x - x0)] = F
        G *= E
        E *= ea
        F *= eb


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _lanes_span(tb, x0, sx0, sx1, ws, nw, G, E, ea):
    """Chord mode: lanes of one row from its span's recurrence (G at sx0, step E times ea); zero in the rest of the
    window [ws, ws + nw). The row-step factors are zeroed too (the blend moves every lane on by them)."""
    for i in range(ws, ws + nw):
        tb[_lane(L_G, i)] = 0.0
        tb[_lane(L_F, i)] = 0.0
    for x in range(sx0, sx1 + 1):
        tb[_lane(L_G, x - x0)] = G
        G *= E
        E *= ea


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _blend_lanes(tb, pb, ws, n, o, f0, f1, f2, f3, f4, f5, f6, f7, kk, ec, eight):
    """``_blend`` on the window of n lanes (32, or 16 or 8 at offset ws) of the tile row starting at pixel pb, adding
    four (eight) features times the weights into the channel planes, and moves the window's exp(power) lanes on to
    the next row (times their factors, the factors times ec); returns how many pixels stopped. Call it with literal n
    and eight (it is inlined: they become constants, so the loop is vectorised). The move to the next row runs in the
    same loop rather than a loop of its own: one loop set-up per row less, which pays on rows of wide Gaussians
    (captured fr3/cabinet renders at 640x480: forward 36.4 -> 34.5 ms, backward 51.0 -> 47.6 ms; the throughput
    scene's small Gaussians: forward +0.2 ms, backward -0.3 ms)."""
    upb = np.uint64(pb) & ROW_MASK
    uws = np.uint64(ws) & WIN_MASK
    nstop = 0
    for i in range(n):
        li = uws + np.uint64(i)
        p = upb + li
        tp = tb[L_T + p]
        g = tb[L_G + li]
        ga = o * g
        tb[L_G + li] = g * tb[L_F + li]  # on to the next row
        tb[L_F + li] *= ec
        alpha = ga if ga < ALPHA_MAX else ALPHA_MAX
        alpha = alpha if alpha >= ALPHA_MIN else 0.0
        nt = tp * (1.0 - alpha)
        stop = (nt < T_MIN) & (tp != 0.0)
        tb[L_S + p] = tp if stop else tb[L_S + p]
        tb[L_T + p] = 0.0 if stop else nt
        w = 0.0 if stop else alpha * tp
        tb[_plane(0, p)] += f0 * w
        tb[_plane(1, p)] += f1 * w
        tb[_plane(2, p)] += f2 * w
        tb[_plane(3, p)] += f3 * w
        if eight:
            tb[_plane(4, p)] += f4 * w
            tb[_plane(5, p)] += f5 * w
            tb[_plane(6, p)] += f6 * w
            tb[_plane(7, p)] += f7 * w
        tb[L_L + p] = kk if w > 0.0 else tb[L_L + p]
        nstop += np.int64(stop)
    return nstop


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _unblend_lanes(tb, pb, ws, n, o, f0, f1, f2, f3, f4, f5, f6, f7, kf, dy, ec, eight):
    """``_unblend`` and ``_unblend_grad`` on the window of n lanes (as ``_blend_lanes``) of the tile row starting at
    pixel pb, for pair index kf (lanes where it lies behind the pixel's last contributor, or whose alpha is below
    ALPHA_MIN, change nothing): moves T and R in front of the pair and adds, per lane, dL/dpower times 1, dy and
    dy^2 and the weight times dL/d(feature) to the lane sums (the pair's sums over x are taken from the lanes when
    the pair ends); moves the lanes on to the next row as ``_blend_lanes`` does."""
    upb = np.uint64(pb) & ROW_MASK
    uws = np.uint64(ws) & WIN_MASK
    dy2 = dy * dy
    for i in range(n):
        li = uws + np.uint64(i)
        p = upb + li
        g = tb[L_G + li]
        ga = o * g
        tb[L_G + li] = g * tb[L_F + li]  # on to the next row
        tb[L_F + li] *= ec
        alpha = ga if ga < ALPHA_MAX else ALPHA_MAX
        ok = (alpha >= ALPHA_MIN) & (kf < tb[L_L + p])
        iom = 1.0 / (1.0 - alpha)
        tp = tb[L_T + p]
        ti = tp * iom
        w = alpha * ti
        g0 = tb[_plane(0, p)]
        g1 = tb[_plane(1, p)]
        g2 = tb[_plane(2, p)]
        g3 = tb[_plane(3, p)]
        fg = f0 * g0 + f1 * g1 + f2 * g2 + f3 * g3
        g4 = g5 = g6 = g7 = 0.0
        if eight:
            g4 = tb[_plane(4, p)]
            g5 = tb[_plane(5, p)]
            g6 = tb[_plane(6, p)]
            g7 = tb[_plane(7, p)]
            fg += f4 * g4 + f5 * g5 + f6 * g6 + f7 * g7
        rr = tb[L_S + p]
        dlda = ti * fg - rr * iom
        tb[L_S + p] = rr + fg * w if ok else rr
        tb[L_T + p] = ti if ok else tp
        dpow = ga * dlda if ok & (ga <= ALPHA_MAX) else 0.0  # the alpha clamp has zero gradient where active
        w = w if ok else 0.0
        tb[L_ACC + li] += dpow
        tb[L_ACC + np.uint64(NLANE) + li] += dpow * dy
        tb[L_ACC + np.uint64(2 * NLANE) + li] += dpow * dy2
        tb[L_ACC + np.uint64(3 * NLANE) + li] += w * g0
        tb[L_ACC + np.uint64(4 * NLANE) + li] += w * g1
        tb[L_ACC + np.uint64(5 * NLANE) + li] += w * g2
        tb[L_ACC + np.uint64(6 * NLANE) + li] += w * g3
        if eight:
            tb[L_ACC + np.uint64(7 * NLANE) + li] += w * g4
            tb[L_ACC + np.uint64(8 * NLANE) + li] += w * g5
            tb[L_ACC + np.uint64(9 * NLANE) + li] += w * g6
            tb[L_ACC + np.uint64(10 * NLANE) + li] += w * g7


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _blend_row(tb, pb, ws, nw, C, o, f0, f1, f2, f3, f4, f5, f6, f7, kk, ec):
    """``_blend_lanes`` on the pair's window (nw = 32, or 16 or 8 at offset ws) with C = 4 or 8 channels, each case with
    literal arguments; returns how many pixels stopped."""
    if nw == TILE and C == 8:
        return _blend_lanes(tb, pb, 0, TILE, o, f0, f1, f2, f3, f4, f5, f6, f7, kk, ec, True)
    if nw == TILE:
        return _blend_lanes(tb, pb, 0, TILE, o, f0, f1, f2, f3, 0.0, 0.0, 0.0, 0.0, kk, ec, False)
    if nw == TILE // 2 and C == 8:
        return _blend_lanes(tb, pb, ws, TILE // 2, o, f0, f1, f2, f3, f4, f5, f6, f7, kk, ec, True)
    if nw == TILE // 2:
        return _blend_lanes(tb, pb, ws, TILE // 2, o, f0, f1, f2, f3, 0.0, 0.0, 0.0, 0.0, kk, ec, False)
    if C == 8:
        return _blend_lanes(tb, pb, ws, TILE // 4, o, f0, f1, f2, f3, f4, f5, f6, f7, kk, ec, True)
    return _blend_lanes(tb, pb, ws, TILE // 4, o, f0, f1, f2, f3, 0.0, 0.0, 0.0, 0.0, kk, ec, False)


@njit(cache=True, nogil=True, inline="always", fastmath=FMA)
def _unblend_row(tb, pb, ws, nw, C, o, f0, f1, f2, f3, f4, f5, f6, f7, kf, dy, ec):
    """``_unblend_lanes`` on the pair's window, dispatched as ``_blend_row``."""
    if nw == TILE and C == 8:
        _unblend_lanes(tb, pb, 0, TILE, o, f0, f1, f2, f3, f4, f5, f6, f7, kf, dy, ec, True)
    elif nw == TILE:
        _unblend_lanes(tb, pb, 0, TILE, o, f0, f1, f2, f3, 0.0, 0.0, 0.0, 0.0, kf, dy, ec, False)
    elif nw == TILE // 2 and C == 8:
        _unblend_lanes(tb, pb, ws, TILE // 2, o, f0, f1, f2, f3, f4, f5, f6, f7, kf, dy, ec, True)
    elif nw == TILE // 2:
        _unblend_lanes(tb, pb, ws, TILE // 2, o, f0, f1, f2, f3, 0.0, 0.0, 0.0, 0.0, kf, dy, ec, False)
    elif C == 8:
        _unblend_lanes(tb, pb, ws, TILE // 4, o, f0, f1, f2, f3, f4, f5, f6, f7, kf, dy, ec, True)
    else:
        _unblend_lanes(tb, pb, ws, TILE // 4, o, f0, f1, f2, f3, 0.0, 0.0, 0.0, 0.0, kf, dy, ec, False)


@njit(cache=True, nogil=True, inline="always")
def _tile_box(order, jt, ntx, width, height):
    """Tile ``order[jt]`` of the grid (``ntx`` tiles a row): its index and pixel box x0, y0, x1, y1 (inclusive,
    clipped to the image)."""
    tile = order[jt]
    ty = tile // ntx
    tx = tile - ty * ntx
    x0 = tx * TILE
    y0 = ty * TILE
    return tile, x0, y0, min(x0 + TILE, width) - 1, min(y0 + TILE, height) - 1


@njit(cache=True, nogil=True, fastmath=FMA, error_model="numpy", pipeline_class=_WorkerPipeline)
def _forward_worker(pk, pf, pidx, tile_start, order, bg, width, height, depth_min_alpha, color, depth_raw, extras,
                    depth, tfinal, last, work_bwd, counter):
    """One worker of ``raster_forward``: composites the tiles it takes from ``counter`` until none is left."""
    C = pf.shape[1]
    uC = np.uint64(C)
    ntx = (width + TILE - 1) // TILE
    ntiles = order.shape[0]
    max_pairs = 1
    for t in range(ntiles):
        max_pairs = max(max_pairs, tile_start[t + 1] - tile_start[t])
    NP = TILE * TILE
    lanes = C == 4 or C == 8
    T = np.empty(NP, np.float64)  # running transmittance; 0 once the pixel has stopped
    Tstop = np.empty(NP, np.float64)  # transmittance at the stop
    acc = np.empty(NP * C, np.float64)  # pixel-major: acc[p * C + c]
    lst = np.empty(NP, np.int64)
    # work done up to and including each pair of the tile: the backward's cost ends at the last contributor,
    # read off after the tile (a per-pixel "contributed" flag in the pixel loops cost ~6% of the forward)
    work_at = np.empty(max_pairs, np.float64)
    tb = np.zeros(LANE_BUF, np.float64)  # the lane path's tile state (T, Tstop, lst, acc live here instead)
    while True:
        jt = _fetch_add(counter, np.int64(1))
        if jt >= ntiles:
            break
        tile, x0, y0, x1, y1 = _tile_box(order, jt, ntx, width, height)
        npix = (x1 - x0 + 1) * (y1 - y0 + 1)
        k0 = tile_start[tile]
        if lanes:
            for p in range(NP):
                tb[_lane(L_T, p)] = 1.0
                tb[_lane(L_L, p)] = k0
            for p in range(C * PLANE):
                tb[_lane(L_C, p)] = 0.0
        else:
            T[:] = 1.0
            acc[:] = 0.0
            lst[:] = k0
        ndone = 0
        work = 0.0
        kend = tile_start[tile + 1]
        _prefetch_pair(pk, pf, pidx, k0, kend)
        _prefetch_pair(pk, pf, pidx, k0 + 1, kend)
        for k in range(k0, kend):
            _prefetch_pair(pk, pf, pidx, k + 2, kend)
            j = pidx[k]
            (gx0, gx1, gy0, gy1, mx, my, ca, cb, cc, o, qmax, ea, eb, ec, chord,
             f0, f1, f2, f3) = _load_pair(pk, pf, j, x0, x1, y0, y1)
            if chord:
                Grow, Erow, Fy = 0.0, 0.0, 0.0
            else:
                Grow, Erow, Fy = _pair_start(mx, my, ca, cb, cc, gx0, gy0)
            f4, f5, f6, f7 = _load_extras4(pf, j)
            kk = np.float64(k + 1)
            ws, nw = _window(gx0, gx1, x0)
            if lanes and not chord:
                _lanes_start(tb, x0, gx0, gx1, ws, nw, Grow, Erow, Fy, ea, eb)
            for y in range(gy0, gy1 + 1):
                if chord:
                    sx0, sx1, G, E = _row_span(mx, ca, cb, cc, qmax, my - y, gx0, gx1)
                else:
                    sx0, sx1, G, E = gx0, gx1, Grow, Erow
                    Grow *= Fy
                    Fy *= ec
                    Erow *= eb
                work += max(0, sx1 - sx0 + 1)
                prow = (y - y0) * TILE - x0
                if lanes:
                    if chord:
                        _lanes_span(tb, x0, sx0, sx1, ws, nw, G, E, ea)
                    ndone += _blend_row(tb, (y - y0) * TILE, ws, nw, C, o, f0, f1, f2, f3, f4, f5, f6, f7, kk, ec)
                else:
                    for x in range(sx0, sx1 + 1):
                        g = G
                        G *= E
                        E *= ea
                        p = np.uint64(prow + x)
                        w = _blend(T, Tstop, p, o, g)
                        if w < 0.0:
                            ndone += 1
                            continue
                        q = p * uC
                        acc[q] += f0 * w
                        acc[q + np.uint64(1)] += f1 * w
                        acc[q + np.uint64(2)] += f2 * w
                        acc[q + np.uint64(3)] += f3 * w
                        for c in range(4, C):
                            acc[q + np.uint64(c)] += pf[j, c] * w
                        lst[p] = max(lst[p], (k + 1) * (w > 0.0))
            work_at[k - k0] = work
            if ndone == npix:
                break
        if lanes:
            for p in range(NP):
                lst[p] = np.int64(tb[_lane(L_L, p)])
                T[p] = tb[_lane(L_T, p)]
                Tstop[p] = tb[_lane(L_S, p)]
            for c in range(C):
                for p in range(NP):
                    acc[p * C + c] = tb[_plane(c, p)]
        kl = k0
        for p in range(NP):
            kl = max(kl, lst[p])
        work_bwd[tile] = work_at[kl - k0 - 1] if kl > k0 else 0.0
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                p = (y - y0) * TILE + (x - x0)
                tp = T[p]
                if tp == 0.0:
                    tp = Tstop[p]
                for c in range(3):
                    color[y, x, c] = acc[p * C + c] + tp * bg[c]
                zr = np.float32(acc[p * C + 3])
                depth_raw[y, x] = zr
                for c in range(4, C):
                    extras[y, x, c - 4] = acc[p * C + c]
                tf = np.float32(tp)
                tfinal[y, x] = tf
                a = 1.0 - np.float64(tf)
                depth[y, x] = zr / a if a > depth_min_alpha else 0.0
                last[y, x] = lst[p]


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def raster_forward(pk, pf, pidx, tile_start, order, bg, width, height, depth_min_alpha, color, depth_raw, extras, depth,
                   tfinal, last, work_bwd, nworkers):
    """Front-to-back compositing of the pairs of ``bin_tiles`` (pk = srec, pf = sfeat: depth-ordered records and
    features; pair k reads row pidx[k]). Writes color [H,W,3] (plus bg),
    depth_raw [H,W], extras [H,W,K], depth [H,W] (= depth_raw / alpha where alpha > depth_min_alpha, else 0,
    alpha = 1 - tfinal), tfinal [H,W] (all f32), last [H,W] i64 (one past the pair index of the pixel's last
    contributor), work_bwd [ntiles] f64 (evaluated pixels up to the tile's last contributor: backward cost)."""
    counter = np.zeros(1, np.int64)
    for _w in prange(nworkers):
        _forward_worker(pk, pf, pidx, tile_start, order, bg, width, height, depth_min_alpha, color, depth_raw,
                        extras, depth, tfinal, last, work_bwd, counter)


@njit(cache=True, nogil=True, fastmath=FMA, error_model="numpy", pipeline_class=_WorkerPipeline)
def _backward_worker(pk, pf, pidx, tile_start, order, bg, width, height, depth_min_alpha, g_color, g_depth_raw,
                     g_extras, g_depth, g_alpha, depth_raw, tfinal, last, pg, counter, C, uC, ntx, ntiles, NP, lanes):
    """One worker of ``raster_backward``: the gradients of the tiles it takes from ``counter`` until none is left.
    The loop invariants C .. lanes come from the wrapper, as the parfor passed them (here they ran ~7% slower)."""
    T = np.empty(NP, np.float64)
    Rr = np.empty(NP, np.float64)
    gp = np.zeros(NP * C, np.float64)  # pixel-major dL/dout of the tile
    lst = np.zeros(NP, np.int64)
    gf = np.empty(C, np.float64)
    tb = np.zeros(LANE_BUF, np.float64)  # the lane path's tile state (T, Rr, lst, gp live here instead)
    while True:
        jt = _fetch_add(counter, np.int64(1))
        if jt >= ntiles:
            break
        tile, x0, y0, x1, y1 = _tile_box(order, jt, ntx, width, height)
        k0 = tile_start[tile]
        k1 = tile_start[tile + 1]
        kmax = k0
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                p = (y - y0) * TILE + (x - x0)
                tf = np.float64(tfinal[y, x])
                T[p] = tf
                bgg = 0.0
                for c in range(3):
                    gv = np.float64(g_color[y, x, c])
                    gp[p * C + c] = gv
                    bgg += bg[c] * gv
                gz = np.float64(g_depth_raw[y, x])
                gal = np.float64(g_alpha[y, x])
                a = 1.0 - tf
                if a > depth_min_alpha:  # depth = depth_raw / alpha
                    gd = np.float64(g_depth[y, x])
                    gz += gd / a
                    gal -= gd * np.float64(depth_raw[y, x]) / (a * a)
                gp[p * C + 3] = gz
                for c in range(4, C):
                    gp[p * C + c] = g_extras[y, x, c - 4]
                Rr[p] = tf * (bgg - gal)
                lst[p] = last[y, x]
                kmax = max(kmax, last[y, x])
        if lanes:  # pixels outside the image stay zero: no pair's lanes reach them
            for p in range(PLANE * (3 + C)):
                tb[_lane(L_T, p)] = 0.0
            for y in range(y0, y1 + 1):
                for x in range(x0, x1 + 1):
                    p = (y - y0) * TILE + (x - x0)
                    tb[_lane(L_T, p)] = T[p]
                    tb[_lane(L_S, p)] = Rr[p]
                    tb[_lane(L_L, p)] = lst[p]
                    for c in range(C):
                        tb[_plane(c, p)] = gp[p * C + c]
        pg[kmax:k1] = 0.0  # pairs behind every pixel's last contributor
        _prefetch_pair(pk, pf, pidx, kmax - 1, kmax)
        _prefetch_pair(pk, pf, pidx, kmax - 2, kmax)
        for k in range(kmax - 1, k0 - 1, -1):
            if k >= k0 + 2:
                _prefetch_pair(pk, pf, pidx, k - 2, kmax)
            j = pidx[k]
            (gx0, gx1, gy0, gy1, mx, my, ca, cb, cc, o, qmax, ea, eb, ec, chord,
             f0, f1, f2, f3) = _load_pair(pk, pf, j, x0, x1, y0, y1)
            if chord:
                Grow, Erow, Fy = 0.0, 0.0, 0.0
            else:
                Grow, Erow, Fy = _pair_start(mx, my, ca, cb, cc, gx0, gy0)
            # sums over the pair's pixels of dpow = dL/dpower times 1, dx, dx^2, dy, dx dy, dy^2 (dx, dy:
            # mean minus pixel); the conic and mean gradients are linear in them
            s1t = 0.0
            s2t = 0.0
            sdt = 0.0
            sdyt = 0.0
            sdy2t = 0.0
            s0t = 0.0
            gf0 = 0.0
            gf1 = 0.0
            gf2 = 0.0
            gf3 = 0.0
            for c in range(4, C):
                gf[c] = 0.0
            f4, f5, f6, f7 = _load_extras4(pf, j)
            ws, nw = _window(gx0, gx1, x0)
            if lanes:
                for pl in range(3 + C):
                    for i in range(ws, ws + nw):
                        tb[_lane(L_ACC, pl * NLANE + i)] = 0.0
                if not chord:
                    _lanes_start(tb, x0, gx0, gx1, ws, nw, Grow, Erow, Fy, ea, eb)
            gf4 = 0.0
            gf5 = 0.0
            gf6 = 0.0
            gf7 = 0.0
            for y in range(gy0, gy1 + 1):
                dy = my - y
                if chord:
                    sx0, sx1, G, E = _row_span(mx, ca, cb, cc, qmax, dy, gx0, gx1)
                else:
                    sx0, sx1, G, E = gx0, gx1, Grow, Erow
                    Grow *= Fy
                    Fy *= ec
                    Erow *= eb
                prow = (y - y0) * TILE - x0
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                if lanes:
                    if chord:
                        _lanes_span(tb, x0, sx0, sx1, ws, nw, G, E, ea)
                    _unblend_row(tb, (y - y0) * TILE, ws, nw, C, o, f0, f1, f2, f3, f4, f5, f6, f7, np.float64(k),
                                 dy, ec)
                    continue
                else:
                    for x in range(sx0, sx1 + 1):
                        g = G
                        G *= E
                        E *= ea
                        p = np.uint64(prow + x)
                        if k >= lst[p]:
                            continue
                        ga = o * g
                        w, ti, iom = _unblend(T, p, ga)
                        if w < 0.0:
                            continue
                        q = p * uC
                        g0 = gp[q]
                        g1 = gp[q + np.uint64(1)]
                        g2 = gp[q + np.uint64(2)]
                        g3 = gp[q + np.uint64(3)]
                        fg = f0 * g0 + f1 * g1 + f2 * g2 + f3 * g3
                        gf0 += w * g0
                        gf1 += w * g1
                        gf2 += w * g2
                        gf3 += w * g3
                        for c in range(4, C):
                            gv = gp[q + np.uint64(c)]
                            fg += pf[j, c] * gv
                            gf[c] += w * gv
                        s0, s1, s2 = _unblend_grad(T, Rr, p, fg, w, ti, iom, ga, mx - x, s0, s1, s2)
                s0t += s0
                s1t += s1
                s2t += s2
                sdt += s0 * dy
                sdyt += s1 * dy
                sdy2t += s0 * dy * dy
            if lanes:  # the lanes' sums over y, summed over the box's x (dx = mx - x is the lane's)
                for x in range(gx0, gx1 + 1):
                    i = x - x0
                    dx = mx - x
                    a0 = tb[_lane(L_ACC, i)]
                    a1 = tb[_lane(L_ACC, NLANE + i)]
                    s0t += a0
                    s1t += a0 * dx
                    s2t += a0 * dx * dx
                    sdt += a1
                    sdyt += a1 * dx
                    sdy2t += tb[_lane(L_ACC, 2 * NLANE + i)]
                    gf0 += tb[_lane(L_ACC, 3 * NLANE + i)]
                    gf1 += tb[_lane(L_ACC, 4 * NLANE + i)]
                    gf2 += tb[_lane(L_ACC, 5 * NLANE + i)]
                    gf3 += tb[_lane(L_ACC, 6 * NLANE + i)]
                    if C == 8:
                        gf4 += tb[_lane(L_ACC, 7 * NLANE + i)]
                        gf5 += tb[_lane(L_ACC, 8 * NLANE + i)]
                        gf6 += tb[_lane(L_ACC, 9 * NLANE + i)]
                        gf7 += tb[_lane(L_ACC, 10 * NLANE + i)]
            # power = -0.5 (a dx^2 + c dy^2) - b dx dy: d/dmean_x = -(a dx + b dy), d/dmean_y = -(c dy + b dx)
            gmx = -(ca * s1t + cb * sdt)
            gmy = -(cc * sdt + cb * s1t)
            gca = -0.5 * s2t
            gcc = -0.5 * sdy2t
            gcb = -sdyt
            pg[k, 0] = gmx
            pg[k, 1] = gmy
            pg[k, 2] = gca
            pg[k, 3] = gcb
            pg[k, 4] = gcc
            pg[k, 5] = s0t / o  # dalpha/do = exp(power) = dalpha/dpower / o
            pg[k, 6] = gf0
            pg[k, 7] = gf1
            pg[k, 8] = gf2
            pg[k, 9] = gf3
            if C == 8:
                gf[4], gf[5], gf[6], gf[7] = gf4, gf5, gf6, gf7
            for c in range(4, C):
                pg[k, 6 + c] = gf[c]


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def raster_backward(pk, pf, pidx, tile_start, order, bg, width, height, depth_min_alpha, g_color,
                    g_depth_raw, g_extras, g_depth, g_alpha, depth_raw, tfinal, last, pg, nworkers):
    """Back-to-front gradients from dL/d(color [H,W,3], depth_raw [H,W], extras [H,W,K], depth [H,W],
    alpha [H,W]) (f32; the depth normalisation of ``raster_forward`` is differentiated here, per pixel).
    Writes every row of pg [npairs, 6+C] f32: for pair k, at row k, the sums over its pixels of
    dL/d(mean_x, mean_y, conic_a, conic_b, conic_c, opacity, feat...)."""
    C = pf.shape[1]
    uC = np.uint64(C)
    ntx = (width + TILE - 1) // TILE
    ntiles = order.shape[0]
    NP = TILE * TILE
    counter = np.zeros(1, np.int64)
    lanes = C == 4 or C == 8
    for _w in prange(nworkers):
        _backward_worker(pk, pf, pidx, tile_start, order, bg, width, height, depth_min_alpha, g_color, g_depth_raw,
                         g_extras, g_depth, g_alpha, depth_raw, tfinal, last, pg, counter, C, uC, ntx, ntiles, NP,
                         lanes)


@njit(cache=True, nogil=True, parallel=True, fastmath=FMA)
def project_backward(means, quats, scales, Rcw, tcw, fx, fy, cx, cy, width, height, eps2d, vis, pair_start,
                     slot_pair, pg, g_means, g_quats, g_scales, g_opac, g_colors, g_extras, g_m2d, g_pose_chunks,
                     nworkers):
    """Sum each visible Gaussian's per-pair gradients (its rows of pg, listed in slot_pair), then apply the chain
    rule to the inputs. Writes every row of g_* (the rows ``vis``, ascending, get the gradients, the others zeros:
    the caller need not clear them, ~0.7 ms at 100k Gaussians); g_pose_chunks [ceil(Nv / SOA_CHUNK), 12] receives
    partial sums of dL/dRcw (row-major, 9) and dL/dtcw (3), one row per chunk."""
    n = g_means.shape[0]
    nv = vis.shape[0]
    D = pg.shape[1]
    K = g_extras.shape[1]
    nchunks = g_pose_chunks.shape[0]
    if nchunks * SOA_CHUNK < nv:
        raise ValueError("project_backward: g_pose_chunks needs a row per SOA_CHUNK visible Gaussians")
    Rt, limxp, limxn, limyp, limyn = _view(Rcw, fx, fy, cx, cy, width, height)
    counter = np.zeros(1, np.int64)
    for _w in prange(nworkers):
        gs = np.empty(D, np.float64)
        buf = np.empty((PB_IN + PB_OUT) * SOA_CHUNK, np.float64)
        while True:
            ch = _fetch_add(counter, np.int64(1))
            if ch >= nchunks:
                break
            j0 = min(nv, ch * SOA_CHUNK)
            j1 = min(nv, j0 + SOA_CHUNK)
            qend = pair_start[j1]  # end of the chunk's slots (pair_start has nv + 1 entries)
            for j in range(j0, j1):
                i = vis[j]
                gs[:] = 0.0
                for q in range(pair_start[j], pair_start[j + 1]):
                    if q + PREFETCH_AHEAD < qend:
                        _prefetch(pg, slot_pair[q + PREFETCH_AHEAD])
                        _prefetch_last(pg, slot_pair[q + PREFETCH_AHEAD])
                    k = slot_pair[q]
                    for d in range(D):
                        gs[d] += pg[k, d]
                g_opac[i] = gs[5]
                g_colors[i, 0] = gs[6]
                g_colors[i, 1] = gs[7]
                g_colors[i, 2] = gs[8]
                for c in range(K):
                    g_extras[i, c] = gs[10 + c]
                g_m2d[i, 0] = gs[0]
                g_m2d[i, 1] = gs[1]
                jj = j - j0
                for f in range(5):
                    buf[_field(f, jj)] = gs[f]
                buf[_field(5, jj)] = gs[9]
                _soa_gather_shape(buf, 6, jj, means, quats, scales, i)
            _chain_rule(buf, np.uint64(j1 - j0), Rt, tcw[0], tcw[1], tcw[2], fx, fy, limxp, limxn, limyp, limyn,
                        eps2d)
            for q in range(12):
                g_pose_chunks[ch, q] = 0.0
            # the chunk's rows of the outputs: from past the previous chunk's last visible Gaussian to its own last
            # (the first chunk from row 0, the last to the end)
            lo = 0 if j0 == 0 else vis[j0 - 1] + 1
            hi = n if ch == nchunks - 1 else (vis[j1 - 1] + 1 if j1 > 0 else 0)
            j = j0
            for i in range(lo, hi):
                if j < j1 and vis[j] == i:
                    jj = j - j0
                    for f in range(3):
                        g_means[i, f] = buf[_field(PB_IN + f, jj)]
                    for f in range(4):
                        g_quats[i, f] = buf[_field(PB_IN + 3 + f, jj)]
                    for f in range(3):
                        g_scales[i, f] = buf[_field(PB_IN + 7 + f, jj)]
                    for q in range(12):
                        g_pose_chunks[ch, q] += buf[_field(PB_IN + 10 + q, jj)]
                    j += 1
                else:
                    for f in range(3):
                        g_means[i, f] = 0.0
                        g_scales[i, f] = 0.0
                        g_colors[i, f] = 0.0
                    for f in range(4):
                        g_quats[i, f] = 0.0
                    for c in range(K):
                        g_extras[i, c] = 0.0
                    g_opac[i] = 0.0
                    g_m2d[i, 0] = 0.0
                    g_m2d[i, 1] = 0.0


@njit(cache=True, nogil=True, fastmath=FMA, error_model="numpy", pipeline_class=_WorkerPipeline)
def _chain_rule(buf, n, Rt, t0, t1, t2, fx, fy, limxp, limxn, limyp, limyn, eps2d):
    """The chain rule of ``project_backward`` for the chunk's n Gaussians (buffer fields PB_IN in, PB_OUT out): from
    dL/d(pixel centre, conic, depth) through conic -> 2D covariance -> (Jacobian, world-to-camera rotation, 3D
    covariance) -> quaternion, scales, and through the pixel centre and depth to the mean and the pose."""
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = Rt
    for jj in range(n):
        gmx = buf[_field(0, jj)]
        gmy = buf[_field(1, jj)]
        gA = buf[_field(2, jj)]
        gB = buf[_field(3, jj)]
        gC = buf[_field(4, jj)]
        gz = buf[_field(5, jj)]
        # ---- recompute the forward quantities ----
        pwx, pwy, pwz, x, y, z = _soa_camera_point(buf, 6, jj, Rt, t0, t1, t2)
        qw, qx, qy, qz, qn_raw, qn = _soa_unit_quaternion(buf, 9, jj)
        s0 = buf[_field(13, jj)]
        s1 = buf[_field(14, jj)]
        s2 = buf[_field(15, jj)]
        (r00, r01, r02, r10, r11, r12, r20, r21, r22, m00, m01, m02, m10, m11, m12, m20, m21, m22,
         S00, S01, S02, S11, S12, S22) = _covariance3d(qw, qx, qy, qz, s0, s1, s2)
        rz = 1.0 / z
        rx = x * rz
        ry = y * rz
        clx = rx < -limxn or rx > limxp
        cly = ry < -limyn or ry > limyp
        (tx, ty, j00, j02, j11, j12, a00, a01, a02, a10, a11, a12, u0, u1, u2, v0, v1, v2, ca, cb,
         cc) = _covariance2d(S00, S01, S02, S11, S12, S22, Rt, fx, fy, z, rx, ry, rz, limxp, limxn, limyp, limyn,
                             eps2d)
        idet = 1.0 / (ca * cc - cb * cb)
        qa = cc * idet
        qb = -cb * idet
        qc = ca * idet
        # ---- conic -> Sigma2:  dL/dSigma2 = -Q G Q, G = [[gA, gB/2], [gB/2, gC]] ----
        hb = 0.5 * gB
        t00 = gA * qa + hb * qb
        t01 = gA * qb + hb * qc
        t10 = hb * qa + gC * qb
        t11 = hb * qb + gC * qc
        G00 = -(qa * t00 + qb * t10)
        G01 = -(qa * t01 + qb * t11)
        G11 = -(qb * t01 + qc * t11)
        # ---- Sigma2 = T2 Sigma T2^T:  dL/dT2 = 2 G T2 Sigma,  dL/dSigma = T2^T G T2 ----
        # T2 Sigma rows: (u0,u1,u2) = row0, (v0,v1,v2) = row1
        gT00 = 2.0 * (G00 * u0 + G01 * v0)
        gT01 = 2.0 * (G00 * u1 + G01 * v1)
        gT02 = 2.0 * (G00 * u2 + G01 * v2)
        gT10 = 2.0 * (G01 * u0 + G11 * v0)
        gT11 = 2.0 * (G01 * u1 + G11 * v1)
        gT12 = 2.0 * (G01 * u2 + G11 * v2)
        # G T2 (2x3)
        w00 = G00 * a00 + G01 * a10
        w01 = G00 * a01 + G01 * a11
        w02 = G00 * a02 + G01 * a12
        w10 = G01 * a00 + G11 * a10
        w11 = G01 * a01 + G11 * a11
        w12 = G01 * a02 + G11 * a12
        gS00 = a00 * w00 + a10 * w10
        gS01 = a00 * w01 + a10 * w11
        gS02 = a00 * w02 + a10 * w12
        gS11 = a01 * w01 + a11 * w11
        gS12 = a01 * w02 + a11 * w12
        gS22 = a02 * w02 + a12 * w12
        # ---- Sigma = M M^T:  dL/dM = 2 gS M ----
        gM00 = 2.0 * (gS00 * m00 + gS01 * m10 + gS02 * m20)
        gM01 = 2.0 * (gS00 * m01 + gS01 * m11 + gS02 * m21)
        gM02 = 2.0 * (gS00 * m02 + gS01 * m12 + gS02 * m22)
        gM10 = 2.0 * (gS01 * m00 + gS11 * m10 + gS12 * m20)
        gM11 = 2.0 * (gS01 * m01 + gS11 * m11 + gS12 * m21)
        gM12 = 2.0 * (gS01 * m02 + gS11 * m12 + gS12 * m22)
        gM20 = 2.0 * (gS02 * m00 + gS12 * m10 + gS22 * m20)
        gM21 = 2.0 * (gS02 * m01 + gS12 * m11 + gS22 * m21)
        gM22 = 2.0 * (gS02 * m02 + gS12 * m12 + gS22 * m22)
        buf[_field(PB_IN + 7, jj)] = gM00 * r00 + gM10 * r10 + gM20 * r20
        buf[_field(PB_IN + 8, jj)] = gM01 * r01 + gM11 * r11 + gM21 * r21
        buf[_field(PB_IN + 9, jj)] = gM02 * r02 + gM12 * r12 + gM22 * r22
        G_00 = gM00 * s0
        G_01 = gM01 * s1
        G_02 = gM02 * s2
        G_10 = gM10 * s0
        G_11 = gM11 * s1
        G_12 = gM12 * s2
        G_20 = gM20 * s0
        G_21 = gM21 * s1
        G_22 = gM22 * s2
        gqw = 2.0 * (-qz * G_01 + qy * G_02 + qz * G_10 - qx * G_12 - qy * G_20 + qx * G_21)
        gqx = 2.0 * (qy * G_01 + qz * G_02 + qy * G_10 - 2.0 * qx * G_11 - qw * G_12 + qz * G_20
                     + qw * G_21 - 2.0 * qx * G_22)
        gqy = 2.0 * (-2.0 * qy * G_00 + qx * G_01 + qw * G_02 + qx * G_10 + qz * G_12 - qw * G_20
                     + qz * G_21 - 2.0 * qy * G_22)
        gqz = 2.0 * (-2.0 * qz * G_00 - qw * G_01 + qx * G_02 + qw * G_10 - 2.0 * qz * G_11 + qy * G_12
                     + qx * G_20 + qy * G_21)
        # through the normalisation (zero for a degenerate quaternion)
        dot = qw * gqw + qx * gqx + qy * gqy + qz * gqz
        live = 1.0 if qn_raw >= 1e-12 else 0.0
        buf[_field(PB_IN + 3, jj)] = live * ((gqw - qw * dot) / qn)
        buf[_field(PB_IN + 4, jj)] = live * ((gqx - qx * dot) / qn)
        buf[_field(PB_IN + 5, jj)] = live * ((gqy - qy * dot) / qn)
        buf[_field(PB_IN + 6, jj)] = live * ((gqz - qz * dot) / qn)
        # ---- T2 = J Rcw:  dL/dJ = gT Rcw^T,  dL/dRcw += J^T gT ----
        gJ00 = gT00 * R00 + gT01 * R01 + gT02 * R02
        gJ02 = gT00 * R20 + gT01 * R21 + gT02 * R22
        gJ11 = gT10 * R10 + gT11 * R11 + gT12 * R12
        gJ12 = gT10 * R20 + gT11 * R21 + gT12 * R22
        # ---- J(x, y, z) and the pixel centre and depth ----
        rz2 = rz * rz
        rz3 = rz2 * rz
        gx = fx * rz * gmx
        gy = fy * rz * gmy
        gzz = gz - fx * x * rz2 * gmx - fy * y * rz2 * gmy
        gzz += -fx * rz2 * gJ00 - fy * rz2 * gJ11
        # the x (y) clamp of the Jacobian: its entry then moves with z only
        gx += 0.0 if clx else -fx * rz2 * gJ02
        gzz += fx * tx * rz3 * gJ02 if clx else 2.0 * fx * x * rz3 * gJ02
        gy += 0.0 if cly else -fy * rz2 * gJ12
        gzz += fy * ty * rz3 * gJ12 if cly else 2.0 * fy * y * rz3 * gJ12
        buf[_field(PB_IN + 0, jj)] = R00 * gx + R10 * gy + R20 * gzz
        buf[_field(PB_IN + 1, jj)] = R01 * gx + R11 * gy + R21 * gzz
        buf[_field(PB_IN + 2, jj)] = R02 * gx + R12 * gy + R22 * gzz
        # dL/dRcw: from p = Rcw pw + t  and from T2 = J Rcw
        buf[_field(PB_IN + 10, jj)] = gx * pwx + j00 * gT00
        buf[_field(PB_IN + 11, jj)] = gx * pwy + j00 * gT01
        buf[_field(PB_IN + 12, jj)] = gx * pwz + j00 * gT02
        buf[_field(PB_IN + 13, jj)] = gy * pwx + j11 * gT10
        buf[_field(PB_IN + 14, jj)] = gy * pwy + j11 * gT11
        buf[_field(PB_IN + 15, jj)] = gy * pwz + j11 * gT12
        buf[_field(PB_IN + 16, jj)] = gzz * pwx + j02 * gT00 + j12 * gT10
        buf[_field(PB_IN + 17, jj)] = gzz * pwy + j02 * gT01 + j12 * gT11
        buf[_field(PB_IN + 18, jj)] = gzz * pwz + j02 * gT02 + j12 * gT12
        buf[_field(PB_IN + 19, jj)] = gx
        buf[_field(PB_IN + 20, jj)] = gy
        buf[_field(PB_IN + 21, jj)] = gzz
