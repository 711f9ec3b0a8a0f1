"""Atomic outputs: a failed or interrupted write leaves the previous file whole and no temporary behind."""
import numpy as np
import pytest

from ggfslam.atomic import atomic_path, write_text_atomic
from ggfslam.data.trajectory_io import read_tum_trajectory, write_tum_trajectory


def test_a_completed_write_replaces_the_file_and_leaves_nothing_else(tmp_path):
    target = tmp_path / "metrics.json"
    target.write_text("old")
    write_text_atomic(target, "new")
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


@pytest.mark.parametrize("interruption", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_an_interrupted_write_keeps_the_previous_file(tmp_path, interruption):
    target = tmp_path / "trajectory.txt"
    write_tum_trajectory(target, np.array([0.0, 1.0]), np.stack([np.eye(4)] * 2))
    before = target.read_bytes()
    with pytest.raises(type(interruption)):
        with atomic_path(target) as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".txt" and tmp.name != target.name
            tmp.write_text("0.0 1 2")  # half a file
            raise interruption
    assert target.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["trajectory.txt"]
    stamps, poses = read_tum_trajectory(target)
    assert len(stamps) == 2


def test_a_writer_that_writes_nothing_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="produced no file"):
        with atomic_path(tmp_path / "mesh.ply"):
            pass
    assert not list(tmp_path.iterdir())


def test_a_failing_ply_write_keeps_the_previous_map(tmp_path, monkeypatch):
    from ggfslam.gaussians import ply
    from ggfslam.gaussians.ply import read_gaussians_ply, write_gaussians_ply

    n = 5
    rng = np.random.default_rng(0)
    args = dict(means=rng.normal(size=(n, 3)), quats=np.tile([1.0, 0, 0, 0], (n, 1)), scales=np.full((n, 3), 0.01),
                opacities=np.full(n, 0.5), colors=rng.uniform(size=(n, 3)))
    path = tmp_path / "gaussians.ply"
    write_gaussians_ply(path, **args)
    before = path.read_bytes()

    def broken(*a, **kw):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ply.np, "ascontiguousarray", broken)
    with pytest.raises(OSError, match="No space"):
        write_gaussians_ply(path, **{**args, "means": args["means"] + 1})
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["gaussians.ply"]
    assert len(read_gaussians_ply(path)["means"]) == n
