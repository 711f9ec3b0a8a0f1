"""Gaussians as the standard 3D Gaussian Splatting PLY (INRIA layout) and plain coloured point-cloud PLYs.

The Gaussian layout is the one the original 3DGS code writes and SuperSplat, SIBR, the antimatter15 viewer and the
gsplat tools read: binary little-endian float32 ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2
rot_0..3``, with colours as degree-0 SH coefficients, opacity as a logit, scales as natural logs and rotations as
w, x, y, z quaternions. A bake may carry degree-1 SH (``sh_rest``); the file always holds 45 ``f_rest`` values
(degree 3, the rest zero) because several viewers assume degree 3 from the stride. ``f_rest`` is channel-major as
3DGS writes it: ``f_rest_{c * 15 + j}`` is coefficient j + 1 of colour channel c.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.lib.recfunctions import structured_to_unstructured

from ggfslam.atomic import atomic_path
from ggfslam.errors import DatasetError

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical-harmonic coefficient: rgb = 0.5 + SH_C0 * f_dc."""

N_SH_REST = 45  # degree-3 SH minus the DC term, times 3 channels

GAUSSIAN_PROPERTIES: tuple[str, ...] = (
    ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    + tuple(f"f_rest_{i}" for i in range(N_SH_REST))
    + ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
)
"""Vertex properties of the PLY we write, in file order (all float32)."""

REQUIRED_PROPERTIES: tuple[str, ...] = (
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}

_MAX_HEADER_BYTES = 1 << 20  # a real header is a few kB; this stops a binary non-PLY from being scanned whole

_OPACITY_EPS = 1e-6
_SCALE_MIN = 1e-12


def _as_numpy(name: str, x, shape: tuple[int | None, ...]) -> np.ndarray:
    """``x`` (numpy array or torch tensor) as a float64 array of ``shape`` (None = any), finite, else ValueError."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains {int(np.sum(~np.isfinite(a)))} non-finite values")
    return a


def _atomic_write(path: Path, header: bytes, body: np.ndarray) -> None:
    """Write header + the raw bytes of ``body`` to a temp file, then rename, so readers never see half a file."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        np.ascontiguousarray(body).tofile(f)


def write_gaussians_ply(path, means, quats, scales, opacities, colors, sh_rest=None) -> None:
    """Write Gaussians (means [N,3], wxyz quats [N,4], linear scales [N,3], opacities [N], rgb [N,3] (the DC colour),
    optional SH [N, B, 3] of degree >= 1 (basis B = 3 or 8 or 15, channel)) as a 3DGS PLY."""
    path = Path(path)
    means = _as_numpy("means", means, (None, 3))  # [N, 3]
    n = means.shape[0]
    quats = _as_numpy("quats", quats, (n, 4))  # [N, 4]
    scales = _as_numpy("scales", scales, (n, 3))  # [N, 3]
    if hasattr(opacities, "shape") and tuple(opacities.shape) == (n, 1):
        # models often keep opacities as a column; accept it rather than making every caller squeeze
        opacities = opacities.reshape(n)
    opacities = _as_numpy("opacities", opacities, (n,))  # [N]
    colors = _as_numpy("colors", colors, (n, 3))  # [N, 3]
    rest = None if sh_rest is None else _as_numpy("sh_rest", sh_rest, (n, None, 3))  # [N, B, 3]
    if rest is not None and rest.shape[1] not in (3, 8, 15):
        raise ValueError(f"sh_rest: expected 3, 8 or 15 coefficients per channel (SH degree 1-3), got {rest.shape[1]}")

    qnorm = np.linalg.norm(quats, axis=1, keepdims=True)  # [N, 1]
    if np.any(qnorm == 0):
        raise ValueError(f"quats: {int(np.sum(qnorm == 0))} quaternions have zero norm")
    p = np.clip(opacities, _OPACITY_EPS, 1.0 - _OPACITY_EPS)

    # every property is float32, so a plain [N, 62] array has exactly the packed record layout
    data = np.zeros((n, len(GAUSSIAN_PROPERTIES)), dtype="<f4")  # [N, 62]; normals (and unused f_rest) stay 0
    data[:, 0:3] = means
    data[:, 6:9] = (colors - 0.5) / SH_C0
    if rest is not None:
        per = N_SH_REST // 3
        for c in range(3):
            data[:, 9 + c * per:9 + c * per + rest.shape[1]] = rest[:, :, c]
    o = 9 + N_SH_REST
    data[:, o] = np.log(p) - np.log1p(-p)
    data[:, o + 1:o + 4] = np.log(np.maximum(scales, _SCALE_MIN))
    data[:, o + 4:o + 8] = quats / qnorm

    lines = ["ply", "format binary_little_endian 1.0", "comment generated by ggfslam", f"element vertex {n}"]
    lines += [f"property float {name}" for name in GAUSSIAN_PROPERTIES]
    lines.append("end_header")
    _atomic_write(path, ("\n".join(lines) + "\n").encode("ascii"), data)


def _parse_header(path: Path, f) -> tuple[int, list[tuple[str, int, list[tuple[str, str]]]]]:
    """Header length in bytes and the elements [(name, count, [(property, numpy dtype)])] of a binary LE PLY."""
    first = f.readline(16)
    if first.rstrip(b"\r\n") != b"ply":
        raise DatasetError(path, "not a PLY file (it does not start with 'ply')")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    fmt = None
    lineno = 1
    while True:
        raw = f.readline(_MAX_HEADER_BYTES)
        lineno += 1
        if not raw:
            raise DatasetError(path, "PLY header has no 'end_header' line (file truncated or damaged)")
        if f.tell() > _MAX_HEADER_BYTES:
            raise DatasetError(path, f"PLY header longer than {_MAX_HEADER_BYTES} bytes (damaged file?)")
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise DatasetError(path, "PLY header contains non-ASCII bytes (damaged file?)", lineno) from None
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else ""
            if fmt != "binary_little_endian":
                raise DatasetError(
                    path, f"PLY format '{fmt}' is not supported; expected binary_little_endian "
                    "(the standard 3D Gaussian Splatting layout)", lineno)
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[4], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise DatasetError(path, f"unsupported PLY property line '{line}'", lineno)
        else:
            raise DatasetError(path, f"unexpected PLY header line '{line}'", lineno)
    if fmt is None:
        raise DatasetError(path, "PLY header has no 'format' line")
    return f.tell(), elements


def read_gaussians_ply(path) -> dict[str, np.ndarray]:
    """Read a standard 3DGS PLY: means, quats (wxyz, unit), linear scales, opacities, rgb colors, sh_rest."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "Gaussian PLY file not found (or not a regular file)")
    with open(path, "rb") as f:
        header_len, elements = _parse_header(path, f)
    file_size = path.stat().st_size

    offset = header_len
    vertex = None
    for name, count, props in elements:
        if any(t == "list" for _, t in props):
            if name == "vertex":
                raise DatasetError(path, "PLY vertex element has list properties; not a Gaussian splat file")
            if vertex is None:
                # list elements have no fixed size, so the vertex data after one cannot be located
                raise DatasetError(path, f"PLY element '{name}' with list properties precedes 'vertex'")
            continue
        dtype = np.dtype([(p, t) for p, t in props])
        if name == "vertex":
            vertex = (count, dtype, offset)
            break
        offset += count * dtype.itemsize
    if vertex is None:
        raise DatasetError(path, "PLY file has no 'vertex' element")
    n, dtype, offset = vertex
    for prop in REQUIRED_PROPERTIES:
        if prop not in dtype.names:
            raise DatasetError(
                path, f"PLY vertex element lacks the required property '{prop}' "
                "(expected the 3D Gaussian Splatting layout: x y z f_dc_* opacity scale_* rot_*)")
    rest_names = sorted((p for p in dtype.names if p.startswith("f_rest_")), key=lambda p: int(p[7:]))
    if rest_names != [f"f_rest_{i}" for i in range(len(rest_names))]:
        raise DatasetError(path, f"PLY f_rest_* properties are not numbered 0..{len(rest_names) - 1}")
    need = offset + n * dtype.itemsize
    if file_size < need:
        raise DatasetError(
            path, f"PLY file is truncated: {n} vertices of {dtype.itemsize} bytes need {need} bytes, "
            f"the file has {file_size}")

    rec = np.fromfile(path, dtype=dtype, count=n, offset=offset)  # [N] records

    def cols(names, dtype=np.float64) -> np.ndarray:
        if not names:
            return np.zeros((n, 0), dtype=dtype)
        return structured_to_unstructured(rec[names], dtype=dtype)

    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])  # [N, 4]
    qnorm = np.linalg.norm(quats, axis=1, keepdims=True)  # [N, 1]
    # renderers treat a zero quaternion as no rotation; keep that instead of producing NaNs
    quats = np.where(qnorm > 0, quats / np.where(qnorm > 0, qnorm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    with np.errstate(over="ignore"):
        opacities = 1.0 / (1.0 + np.exp(-rec["opacity"].astype(np.float64)))  # [N]
        scales = np.exp(cols(["scale_0", "scale_1", "scale_2"]))  # [N, 3]
    return {
        "means": cols(["x", "y", "z"]).astype(np.float32),
        "quats": quats.astype(np.float32),
        "scales": scales.astype(np.float32),
        "opacities": opacities.astype(np.float32),
        "colors": (0.5 + SH_C0 * cols(["f_dc_0", "f_dc_1", "f_dc_2"])).astype(np.float32),
        "sh_rest": cols(rest_names, np.float32),
    }


def write_colored_points_ply(path, points, colors) -> None:
    """Write a plain point cloud PLY (float32 xyz, uchar rgb) from points [N,3] and colours [N,3] in [0,1]."""
    path = Path(path)
    points = _as_numpy("points", points, (None, 3))  # [N, 3]
    colors = _as_numpy("colors", colors, (points.shape[0], 3))  # [N, 3]
    rec = np.empty(points.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                           ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = points.T
    rgb = np.rint(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)  # [N, 3]
    rec["red"], rec["green"], rec["blue"] = rgb.T
    lines = ["ply", "format binary_little_endian 1.0", "comment generated by ggfslam",
             f"element vertex {points.shape[0]}",
             "property float x", "property float y", "property float z",
             "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    _atomic_write(path, ("\n".join(lines) + "\n").encode("ascii"), rec)
