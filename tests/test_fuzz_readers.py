"""Property-based fuzzing of every file ggfslam reads from a user: whatever a file holds, opening the dataset
(and reading each of its frames) or loading the config gives a working object or a one-line GGFSlamError naming
the file, never another exception. Each test starts from a valid toy dataset and damages one file: random
text or bytes, or the valid content with lines dropped, repeated, swapped or truncated and fields replaced by
hostile values."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ggfslam.config import load_config, save_config
from ggfslam.data.registry import open_dataset
from ggfslam.errors import GGFSlamError

# the default suite replays the same 150 cases per file (stable CI); GGFSLAM_FUZZ_EXAMPLES=N draws N new ones
EXAMPLES = int(os.environ.get("GGFSLAM_FUZZ_EXAMPLES", 150))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize="GGFSLAM_FUZZ_EXAMPLES" not in os.environ,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
HOSTILE = ["", " ", "nan", "NaN", "inf", "-inf", "1e400", "-1e400", "-0", "0", "-1", "1e-320", "abc", "#", "\t",
           "0x10", "1,5", "\u00e9", "\x00", "9" * 40, "../../outside.png", "{", "[", ":", "'", "null", "true"]


@st.composite
def damaged(draw, valid: str) -> str | bytes:
    """A damaged version of a valid text file."""
    how = draw(st.sampled_from(["edit", "edit", "edit", "text", "bytes"]))
    if how == "text":
        return draw(st.text(max_size=400))
    if how == "bytes":
        return draw(st.binary(max_size=400))
    lines = valid.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            lines = [draw(st.sampled_from(HOSTILE))]
        i = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["drop", "repeat", "swap", "truncate", "field", "field", "append"]))
        if op == "drop":
            del lines[i]
        elif op == "repeat":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "truncate":
            lines[i] = lines[i][: draw(st.integers(0, max(len(lines[i]) - 1, 0)))]
        elif op == "append":
            lines.append(" ".join(draw(st.lists(st.sampled_from(HOSTILE), max_size=9))))
        else:
            fields = lines[i].split(" ")
            fields[draw(st.integers(0, len(fields) - 1))] = draw(st.sampled_from(HOSTILE))
            lines[i] = " ".join(fields)
    return "\n".join(lines) + draw(st.sampled_from(["\n", ""]))


def _write(path: Path, content: str | bytes) -> None:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_bytes(content.encode("utf-8", "surrogatepass"))


def _open_auto(root: Path):
    return open_dataset("auto", root)


def _opens_or_says_why(base: Path, rel: str, content, open_fn=_open_auto) -> None:
    """Copy the dataset, put ``content`` into its file ``rel``, open it and read every frame."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / base.name
        shutil.copytree(base, root)
        _write(root / rel, content)
        try:
            ds = open_fn(root)
            for i in range(len(ds)):
                ds[i]
        except GGFSlamError as e:
            msg = str(e)
            assert "\n" not in msg.strip() and "Traceback" not in msg, msg
            assert str(root) in msg, f"the message names no file of the dataset: {msg}"


def _fuzz_file(builder, rel: str):
    base = builder()
    valid = (base / rel).read_text()

    @FUZZ
    @given(content=damaged(valid))
    def check(content):
        _opens_or_says_why(base, rel, content)

    check()


def test_fuzz_tum_colour_list(make_tum):
    _fuzz_file(make_tum, "rgb.txt")


def test_fuzz_tum_depth_list(make_tum):
    _fuzz_file(make_tum, "depth.txt")


def test_fuzz_tum_groundtruth(make_tum):
    _fuzz_file(make_tum, "groundtruth.txt")


def test_fuzz_camera_yaml(make_tum):
    _fuzz_file(make_tum, "camera.yaml")


def test_fuzz_replica_trajectory(make_replica):
    _fuzz_file(make_replica, "traj.txt")


def test_fuzz_replica_cam_params(make_replica):
    _fuzz_file(make_replica, "cam_params.json")


def test_fuzz_scannet_pose(make_scannet):
    _fuzz_file(make_scannet, "pose/2.txt")


def test_fuzz_scannet_intrinsics(make_scannet):
    _fuzz_file(make_scannet, "intrinsic/intrinsic_depth.txt")


def test_fuzz_config_yaml(tmp_path):
    from ggfslam.config import Config

    base = tmp_path / "config.yaml"
    save_config(Config.model_validate({"dataset": {"kind": "synthetic"}}), base)
    valid = base.read_text()

    @FUZZ
    @given(content=damaged(valid))
    def check(content):
        path = tmp_path / "fuzzed.yaml"
        _write(path, content)
        try:
            load_config(path)
        except GGFSlamError as e:
            assert "\n" not in str(e).strip() and str(path) in str(e), str(e)

    check()


_KEYS = ["dataset.stride", "dataset.kind", "mapping.voxel_size", "mapping.train_width", "tracking.n_features",
         "ggf.tau", "gcgr.enabled", "runtime.seed", "mapping", "nosuch.key", "dataset.synthetic.n_frames", "",
         "dataset..stride", "mapping.lambda_ssim"]


@FUZZ
@given(key=st.one_of(st.sampled_from(_KEYS), st.text(max_size=30)),
       value=st.one_of(st.sampled_from(HOSTILE + ["[1, 2]", "{a: 1}", "- x", "1.5", "300", "-4", "synthetic"]),
                       st.text(max_size=30)),
       sep=st.sampled_from(["=", "=", " = ", ":", ""]))
def test_fuzz_set_overrides(key, value, sep):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "config.yaml"
        path.write_text(yaml.safe_dump({"dataset": {"kind": "synthetic"}}))
        try:
            load_config(path, [f"{key}{sep}{value}"])
        except GGFSlamError as e:
            assert "\n" not in str(e).strip(), str(e)


def test_what_fuzzing_found(make_tum, tmp_path):
    """Inputs that once raised a bare exception or a multi-line message."""
    base = make_tum()
    for rel in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        _opens_or_says_why(base, rel, b",")  # a line of separators: IndexError
    for content in (b"\x80", b"dataset:\n  kind: \x00"):  # not UTF-8: UnicodeDecodeError; NUL: a 2-line message
        path = tmp_path / "config.yaml"
        path.write_bytes(content)
        try:
            load_config(path)
            raise AssertionError("expected a ConfigError")
        except GGFSlamError as e:
            assert "\n" not in str(e) and str(path) in str(e), str(e)
    path = tmp_path / "ok.yaml"
    path.write_text("dataset:\n  kind: synthetic\n")
    try:
        load_config(path, ["0\n1=2"])  # a key with a line break: echoed raw
        raise AssertionError("expected a ConfigError")
    except GGFSlamError as e:
        assert "\n" not in str(e), str(e)
