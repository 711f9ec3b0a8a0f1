"""Compiling the kernels side by side (``ggfslam/kernel_warmup.py``): what the parts compile is what a run uses, and
the marker that lets later runs skip the compile."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ggfslam import kernel_warmup as kw

SIGNATURES = """
import json, sys
import numba
import ggfslam
from ggfslam import kernel_warmup as kw

def signatures():
    out = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("ggfslam"):
            continue
        for attr, obj in list(vars(mod).items()):
            if isinstance(obj, numba.core.registry.CPUDispatcher):
                out[f"{name}.{attr}"] = sorted(str(s) for s in obj.signatures)
    return out

for part in kw.PARTS:
    kw._run_part(part)
before = signatures()
# what a run does: tracking, a mapper's seeding and training steps rendered by the compiled rasterizer at 320x240,
# and a render with an extra channel (as the viewer's planar-weight renders), forward and backward
from ggfslam.config import config_from_dict
from ggfslam.data.types import Camera
import numpy as np, torch
cfg = config_from_dict({"dataset": {"kind": "synthetic"}})
cam = Camera(320.0, 320.0, 159.5, 119.5, 320, 240, 1000.0)
kw.load_kernels(cfg, cam, mapping=True, backend="cpu")
from ggfslam.render import rasterize
from ggfslam.render.scenes import random_gaussians
sc = {k: torch.from_numpy(v).requires_grad_(True) for k, v in random_gaussians(50, seed=1, n_extras=1).items()}
out = rasterize(**sc, camera=(60.0, 58.0, 31.5, 23.5, 64, 48), T_cw=np.eye(4), backend="cpu")
(out.color.sum() + out.depth.sum() + out.extras.sum()).backward()
after = signatures()
print(json.dumps({k: v for k, v in after.items() if v != before.get(k, [])}))
"""


def test_the_parts_compile_every_kernel_a_training_step_and_tracking_use():
    """After the parts ran, tracking, seeding, training steps (CPU rasterizer) and a render with extras add no
    specialization: a worker's cache entries are the ones a run looks up (types, layouts and all)."""
    res = subprocess.run([sys.executable, "-c", SIGNATURES], capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    new = json.loads(res.stdout.strip().splitlines()[-1])
    assert new == {}, new


def test_cpu_compile_kernels_names_its_stages():
    from ggfslam.render.cpu import KERNEL_STAGES, compile_kernels

    assert set(KERNEL_STAGES) <= set(kw.PARTS)
    with pytest.raises(ValueError, match="composite_forward"):
        compile_kernels("everything")


def test_marker_follows_the_kernel_sources(tmp_path, monkeypatch):
    """No marker: not compiled. A marker for this key: compiled. A kernel module edited: not compiled again."""
    src = tmp_path / "kernels.py"
    src.write_text("@njit(cache=True)\n")
    monkeypatch.setattr(kw, "_kernel_sources", lambda: [src])
    monkeypatch.setattr(kw, "_PACKAGE", tmp_path)
    monkeypatch.setattr(kw, "_cache_dir", lambda: tmp_path / "cache")
    (tmp_path / "cache").mkdir()
    assert not kw.kernels_compiled()
    kw._write_marker(tmp_path / "cache", {"mapping": 1.0}, 1.0, 2)
    assert kw.kernels_compiled()
    assert len(list((tmp_path / "cache").glob(f"{kw.MARKER_PREFIX}*.json"))) == 1
    stat = src.stat()
    os.utime(src, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert not kw.kernels_compiled()
    kw._write_marker(tmp_path / "cache", {"mapping": 1.0}, 1.0, 2)  # replaces the stale marker
    assert kw.kernels_compiled()
    assert len(list((tmp_path / "cache").glob(f"{kw.MARKER_PREFIX}*.json"))) == 1


def test_nothing_to_do_starts_no_process(tmp_path, monkeypatch):
    monkeypatch.setattr(kw, "_cache_dir", lambda: tmp_path)
    started = []
    monkeypatch.setattr(kw, "KernelCompile", lambda *a: started.append(a))
    assert kw.compile_kernels(jobs=0) is None  # turned off
    kw._write_marker(tmp_path, {}, 0.0, 1)
    assert kw.compile_kernels(jobs=2) is None  # compiled already
    assert started == []


def test_kernel_sources_are_the_cached_kernel_modules():
    names = {p.name for p in kw._kernel_sources()}
    assert {"kernels_cpu.py", "child_head.py", "loss_kernels.py", "matching.py", "depth.py"} <= names
    assert "kernel_warmup.py" not in names and "slam.py" not in names


@pytest.mark.slow
def test_a_fresh_cache_is_filled_side_by_side(tmp_path):
    """Two workers compile every part into an empty cache and leave the marker; a run's kernels then load."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    res = subprocess.run([sys.executable, "-m", "ggfslam.kernel_warmup", "--jobs", "2"], env=env,
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    markers = list(Path(tmp_path).glob(f"{kw.MARKER_PREFIX}*.json"))
    assert len(markers) == 1
    info = json.loads(markers[0].read_text())
    assert set(info["parts_seconds"]) == set(kw.PARTS) and info["processes"] == 2
    check = ("import ggfslam, numba; from ggfslam import kernel_warmup as kw; assert kw.kernels_compiled(); "
             "print(kw.compile_kernels(jobs=2))")
    res = subprocess.run([sys.executable, "-c", check], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and res.stdout.strip() == "None", res.stderr[-2000:]


def test_compile_kernels_command(tmp_path, monkeypatch):
    """`ggfslam compile-kernels`: says when there is nothing to do; --jobs 0 compiles nothing and fails."""
    from typer.testing import CliRunner

    from ggfslam.cli import app

    monkeypatch.setattr(kw, "_cache_dir", lambda: tmp_path)
    res = CliRunner().invoke(app, ["compile-kernels", "--jobs", "0"])
    assert res.exit_code == 1 and "nothing compiled" in res.output
    kw._write_marker(tmp_path, {}, 0.0, 1)
    res = CliRunner().invoke(app, ["compile-kernels"])
    assert res.exit_code == 0 and "compiled already" in res.output


def test_an_unwritable_cache_leaves_the_run_to_compile(tmp_path, monkeypatch):
    """A cache folder that cannot be made (here: a file in its way) is a warning, not a failed run."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setattr(kw, "_cache_dir", lambda: blocker / "numba")
    assert kw.compile_kernels(jobs=2) is None
