"""Planarity of a map against a labelled ground-truth mesh: do anchors on planar faces end up planar?"""
from __future__ import annotations

import numpy as np
import open3d as o3d


def closest_triangles(mesh: o3d.geometry.TriangleMesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index [N] of the closest triangle of ``mesh`` to each point [N, 3] and the distance [N] (m)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    res = scene.compute_closest_points(q)
    tri = res["primitive_ids"].numpy().astype(np.int64)
    dist = np.linalg.norm(res["points"].numpy() - np.asarray(points, np.float32), axis=1)
    return tri, dist


def planar_fractions(points: np.ndarray, p2d: np.ndarray, mesh: o3d.geometry.TriangleMesh,
                     triangle_planar: np.ndarray, threshold: float = 0.6, max_dist: float = 0.05) -> dict:
    """Fraction of anchors with P_2D > threshold among those on planar faces and on curved objects.

    points [N, 3]: the anchors' surface points; p2d [N]; ``triangle_planar`` [F] bool labels of the mesh's
    triangles. Anchors farther than ``max_dist`` (m) from the mesh (floaters) are left out."""
    tri, dist = closest_triangles(mesh, points)
    near = dist <= max_dist
    planar = near & triangle_planar[tri]
    curved = near & ~triangle_planar[tri]
    hi = np.asarray(p2d) > threshold
    return {"planar_anchors": int(planar.sum()), "curved_anchors": int(curved.sum()),
            "far_anchors": int((~near).sum()),
            "planar_face_fraction": float(hi[planar].mean()) if planar.any() else float("nan"),
            "curved_object_fraction": float(hi[curved].mean()) if curved.any() else float("nan")}
