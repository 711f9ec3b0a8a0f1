"""Export of the SLAM factor graph (keyframes, landmarks, factors with their current errors) as JSON.

The factors are the ones local bundle adjustment builds (``graph.observation_factor``: a robust virtual-stereo
factor per RGB-D observation, a robust projection factor without depth; ``BetweenFactorPose3`` for a
dense-odometry link), evaluated at the map's current estimates. Per factor two numbers are written:

* ``error``: exactly GTSAM's ``factor.error(values)``. The observation factors carry a Huber kernel, so this
  is 0.5 ||w||^2 for ||w|| <= k and k ||w|| - 0.5 k^2 beyond (w: residual / sigma, k: the Huber threshold).
* ``chi2``: ||w||^2 without the kernel, what the outlier tests compare with the chi-square bounds.

Observation errors are computed in numpy with GTSAM's formulas (thousands of factors per keyframe would take
seconds one GTSAM call at a time); tests check them against ``factor.error`` on a sample.

Layout (``FORMAT_VERSION``); keys are GTSAM symbols written as ``"x3"`` (keyframe 3) / ``"l120"`` (landmark 120),
with their integer values in ``gtsam_keys``:

* ``meta``: version, camera, virtual_baseline, sigmas and Huber thresholds, counts, per-type count and error sum;
* ``keyframes``: id, key, frame_index, timestamp, T_wc (4x4 camera-to-world), n_landmarks (living ones seen);
* ``landmarks``: id, key, position (world), observations (keyframes seeing it);
* ``planes``: id, key (``"p2"``), coefficients (world n, d with n . x + d = 0), observations;
* ``factors``: type (``rgbd_stereo`` | ``projection`` | ``odometry_link`` | ``loop`` | ``plane`` | ``gcgr_depth`` |
  ``gcgr_normal``), keys, gtsam_keys, error, chi2; observations add kf, lm, kp, uv, depth (0: none), sigma; links
  add kf, other_kf, T_other_this; plane factors add kf, plane, measured (camera-frame coefficients); GCGR factors
  (with GCGR on: those of the keyframes whose model the source holds, i.e. what the latest local BAs used) add
  kf, pixels ([u, v] at ``resolution`` = [width, height] of the factors), valid (rows with a map surface),
  sigma (of one row), map_iteration (of the render they linearize) and rows_rmse (root mean square of the
  unwhitened rows at the keyframe's current pose: metres for depth, ``0.05 (1 - cos)`` for normals). Their ``error`` is GTSAM's, from the factor's first-order model (no render);
* ``covisibility``: kf_a < kf_b, shared (living landmarks both see), only pairs sharing >= MIN_COVISIBILITY;
* ``retired_keyframes``: keyframes culled from the graph (``backend.keyframe_culling``; no factors): id,
  frame_index, timestamp, parent (the keyframe in the graph whose pose carries it), T_parent_kf, T_wc.
"""
from __future__ import annotations

import json
from pathlib import Path

import gtsam
import numpy as np

from ggfslam.atomic import write_text_atomic
from ggfslam.backend.graph import L, P, X, huber_loss, observation_errors, odometry_link_factor, plane_factor
from ggfslam.backend.slam_map import SlamMap
from ggfslam.config import BackendConfig, TrackingConfig
from ggfslam.data.types import Camera

__all__ = ["FORMAT_VERSION", "graph_to_dict", "write_graph_json", "load_graph_networkx", "observation_errors",
           "huber_loss", "MIN_COVISIBILITY"]

FORMAT_VERSION = "ggfslam-graph/4"  # 2: plane landmarks and plane factors; 3: GCGR factors; 4: retired keyframes
MIN_COVISIBILITY = 15  # shared landmarks for a covisibility edge (local BA's min_shared)


def _key_name(kind: str, i: int) -> str:
    return f"{kind}{i}"


def graph_to_dict(smap: SlamMap, camera: Camera, tcfg: TrackingConfig, bcfg: BackendConfig, gcgr=None) -> dict:
    """The map's factor graph as a JSON-ready dict (see the module docstring); ``gcgr``: a ``GCGRSource``."""
    level_scale = tcfg.scale_factor ** np.arange(tcfg.n_levels)  # [L]
    with smap.lock:  # one consistent snapshot even if a backend thread is still running
        kf_ids = sorted(smap.keyframes)
        kfs = [smap.keyframes[k] for k in kf_ids]
        poses = {k: smap.keyframes[k].T_wc.copy() for k in kf_ids}
        retired = [{"id": r.id, "frame_index": int(r.frame_index), "timestamp": float(r.timestamp),
                    "parent": int(r.parent), "T_parent_kf": r.T_parent_kf.tolist(), "T_wc": smap.pose(r.id).tolist()}
                   for _, r in sorted(smap.retired.items())]
        lm_ids = smap.alive_ids()  # [P]
        positions = smap.positions[lm_ids].copy()  # [P, 3]
        obs_kf, obs_lm, obs_kp = [], [], []
        for lm in lm_ids:
            for k, kp in smap.observations[lm].items():
                if k in poses:
                    obs_kf.append(k)
                    obs_lm.append(int(lm))
                    obs_kp.append(kp)
        links = [(kf.id, *kf.meta["odometry_link"]) for kf in kfs if "odometry_link" in kf.meta]
        loops = list(smap.loops)
        n_obs_per_lm = {int(lm): len(smap.observations[lm]) for lm in lm_ids}
        kf_n_landmarks = {}
        for kf in kfs:
            ids = kf.landmark_ids[kf.landmark_ids >= 0]
            kf_n_landmarks[kf.id] = int(smap.alive[ids].sum())
        feats = {k: smap.keyframes[k].features for k in kf_ids}
        planes = {pid: pw.copy() for pid, pw in smap.planes.items()}
        plane_obs = [(k, pid, z.copy()) for pid, obs in smap.plane_observations.items() for k, z in obs.items()
                     if k in poses]

    obs_kf = np.asarray(obs_kf, dtype=np.int64)  # [M]
    obs_lm = np.asarray(obs_lm, dtype=np.int64)  # [M]
    obs_kp = np.asarray(obs_kp, dtype=np.int64)  # [M]
    m = len(obs_kf)
    uv, depth, octave = np.zeros((m, 2)), np.zeros(m), np.zeros(m, dtype=np.int64)
    for k in np.unique(obs_kf):  # gather keypoint data per keyframe (vectorised within each)
        sel = np.nonzero(obs_kf == k)[0]
        f = feats[int(k)]
        uv[sel] = f.uv[obs_kp[sel]]
        depth[sel] = f.depth[obs_kp[sel]]
        octave[sel] = f.octave[obs_kp[sel]]
    sigma = tcfg.pixel_sigma * level_scale[octave]  # [M]
    lm_row = np.searchsorted(lm_ids, obs_lm)  # [M] row of each observed landmark (alive_ids is sorted)
    kf_row = np.searchsorted(kf_ids, obs_kf)  # [M]
    pose_all = np.stack([poses[k] for k in kf_ids]) if kf_ids else np.zeros((0, 4, 4))  # [K, 4, 4]
    error, chi2 = observation_errors(pose_all[kf_row], positions[lm_row], uv, depth, sigma, camera,
                                     tcfg.virtual_baseline, bcfg.huber_stereo, bcfg.huber_mono)

    factors = []
    for i in range(m):
        k, lm = int(obs_kf[i]), int(obs_lm[i])
        factors.append({
            "type": "rgbd_stereo" if depth[i] > 0 else "projection",
            "keys": [_key_name("x", k), _key_name("l", lm)], "gtsam_keys": [X(k), L(lm)],
            "kf": k, "lm": lm, "kp": int(obs_kp[i]), "uv": uv[i].tolist(), "depth": float(depth[i]),
            "sigma": float(sigma[i]),
            "error": float(error[i]), "chi2": float(chi2[i]),
        })
    # links, loops and plane observations are few: GTSAM evaluates them directly (the factors local_ba builds)
    values = gtsam.Values()
    for k, T in poses.items():
        values.insert(X(k), gtsam.Pose3(T))
    for pid, pw in planes.items():
        values.insert(P(pid), gtsam.OrientedPlane3(*pw))

    def pose_pair(kind: str, other: int, this: int, T_other_this: np.ndarray, factor) -> dict:
        err = float(factor.error(values))
        return {"type": kind, "keys": [_key_name("x", other), _key_name("x", this)], "gtsam_keys": [X(other), X(this)],
                "kf": int(this), "other_kf": int(other), "T_other_this": np.asarray(T_other_this).tolist(),
                "error": err, "chi2": 2.0 * err}

    for k, other, T_other_k in links:
        if other in poses:
            factors.append(pose_pair("odometry_link", other, k, T_other_k,
                                     odometry_link_factor(other, k, T_other_k, tcfg.dense_link_sigmas)))
    for match, query, T_mq, cov in loops:
        if match in poses and query in poses:
            noise = gtsam.noiseModel.Gaussian.Covariance(cov)
            factors.append(pose_pair("loop", match, query, T_mq,
                                     gtsam.BetweenFactorPose3(X(match), X(query), gtsam.Pose3(T_mq), noise)))
    for k, pid, z in plane_obs:
        err = float(plane_factor(k, pid, z, bcfg.plane_sigmas).error(values))
        factors.append({
            "type": "plane", "keys": [_key_name("x", k), _key_name("p", pid)], "gtsam_keys": [X(k), P(pid)],
            "kf": int(k), "plane": int(pid), "measured": z.tolist(), "error": err, "chi2": 2.0 * err,
        })

    if gcgr is not None:
        factors += _gcgr_factors(gcgr, values, poses)

    # covisibility: shared living landmarks per keyframe pair = off-diagonal of A A^T (A: keyframe x landmark)
    covis = []
    if m:
        from scipy.sparse import coo_matrix

        A = coo_matrix((np.ones(m), (kf_row, lm_row)), shape=(len(kf_ids), len(lm_ids))).tocsr()
        S = (A @ A.T).tocoo()
        for a, b, c in zip(S.row, S.col, S.data):
            if a < b and c >= MIN_COVISIBILITY:
                covis.append({"kf_a": kf_ids[a], "kf_b": kf_ids[b], "shared": int(c)})
        covis.sort(key=lambda e: (e["kf_a"], e["kf_b"]))

    by_type: dict[str, dict] = {}
    for f in factors:
        d = by_type.setdefault(f["type"], {"count": 0, "error": 0.0})
        d["count"] += 1
        d["error"] += f["error"]
    return {
        "meta": {
            "version": FORMAT_VERSION, "camera": camera.to_dict(), "virtual_baseline": tcfg.virtual_baseline,
            "pixel_sigma": tcfg.pixel_sigma, "scale_factor": tcfg.scale_factor,
            "huber_stereo": bcfg.huber_stereo, "huber_mono": bcfg.huber_mono,
            "dense_link_sigmas": list(tcfg.dense_link_sigmas), "min_covisibility": MIN_COVISIBILITY,
            "error_definition": "GTSAM factor.error (Huber kernel on observations); chi2 = squared whitened "
                                "residual without kernel",
            "plane_sigmas": list(bcfg.plane_sigmas),
            "counts": {"keyframes": len(kf_ids), "retired_keyframes": len(retired), "landmarks": len(lm_ids),
                       "planes": len(planes),
                       "factors": len(factors),
                       "observations": m, "covisibility_edges": len(covis)},
            "factors_by_type": by_type,
        },
        "keyframes": [{"id": kf.id, "key": _key_name("x", kf.id), "frame_index": int(kf.frame_index),
                       "timestamp": float(kf.timestamp), "T_wc": poses[kf.id].tolist(),
                       "n_landmarks": kf_n_landmarks[kf.id]} for kf in kfs],
        "landmarks": [{"id": int(lm), "key": _key_name("l", int(lm)), "position": positions[i].tolist(),
                       "observations": n_obs_per_lm[int(lm)]} for i, lm in enumerate(lm_ids)],
        "planes": [{"id": int(pid), "key": _key_name("p", int(pid)), "coefficients": pw.tolist(),
                    "observations": sum(1 for _, q, _ in plane_obs if q == pid)} for pid, pw in sorted(planes.items())],
        "factors": factors,
        "covisibility": covis,
        "retired_keyframes": retired,
    }


def _gcgr_factors(gcgr, values: gtsam.Values, poses: dict[int, np.ndarray]) -> list[dict]:
    """The GCGR factors of the keyframes whose model the source holds, at the keyframes' current poses."""
    out = []
    for k, (model, iteration) in sorted(gcgr.cached_models().items()):
        if k not in poses:
            continue
        w = model.sensor.intr.width
        uv = np.stack([model.pixels % w, model.pixels // w], axis=1)  # [N, 2]
        for kind, factor in model.factors().items():
            err = float(factor.error(values))
            rows = model.evaluate(kind, gtsam.Pose3(poses[k]))  # [N] first-order model, no render
            out.append({
                "type": f"gcgr_{kind}", "keys": [_key_name("x", k)], "gtsam_keys": [X(k)], "kf": int(k),
                "pixels": uv.tolist(), "resolution": [w, model.sensor.intr.height],
                "valid": int(model.valid.sum()), "sigma": model.row_sigma, "map_iteration": int(iteration),
                "rows_rmse": float(np.sqrt(np.mean(rows ** 2))) if len(rows) else 0.0,
                "error": err, "chi2": float(np.sum((rows / model.row_sigma) ** 2)),
            })
    return out


def write_graph_json(path: str | Path, smap: SlamMap, camera: Camera, tcfg: TrackingConfig,
                     bcfg: BackendConfig, gcgr=None) -> dict:
    """Write the factor graph to ``path`` (compact JSON, atomically) and return its dict."""
    path = Path(path)
    data = graph_to_dict(smap, camera, tcfg, bcfg, gcgr)
    # compact: tens of thousands of factors; indentation would triple the file
    write_text_atomic(path, json.dumps(data, separators=(",", ":")) + "\n")
    return data


def load_graph_networkx(path: str | Path):
    """A networkx.Graph of a graph.json: keyframe, landmark and plane nodes (by key), one edge per two-key factor;
    one-key factors (GCGR) are listed on their keyframe's node under ``unary_factors``."""
    try:
        import networkx as nx
    except ImportError:
        raise ImportError("load_graph_networkx needs networkx: pip install networkx") from None
    data = json.loads(Path(path).read_text())
    g = nx.Graph(meta=data["meta"], covisibility=data["covisibility"])
    for kf in data["keyframes"]:
        g.add_node(kf["key"], kind="keyframe", **{k: v for k, v in kf.items() if k != "key"})
    for lm in data["landmarks"]:
        g.add_node(lm["key"], kind="landmark", **{k: v for k, v in lm.items() if k != "key"})
    for pl in data.get("planes", []):
        g.add_node(pl["key"], kind="plane", **{k: v for k, v in pl.items() if k != "key"})
    for f in data["factors"]:
        if len(f["keys"]) == 1:
            g.nodes[f["keys"][0]].setdefault("unary_factors", []).append(f)
            continue
        a, b = f["keys"]
        g.add_edge(a, b, **{k: v for k, v in f.items() if k != "keys"})
    return g
