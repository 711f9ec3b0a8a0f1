"""Typed configuration: every shipped config validates, overrides apply, bad input gives one clear line."""
from pathlib import Path

import pytest

from ggfslam.config import (
    Config, apply_overrides, config_from_dict, describe_fields, expand_path, load_config, save_config,
)
from ggfslam.errors import ConfigError, DatasetError

# run configurations; configs/plans/ holds batch plans (validated in tests/test_batch_plan.py)
CONFIGS = sorted(p for p in (Path(__file__).parents[1] / "configs").rglob("*.yaml") if p.parent.name != "plans")


def test_configs_folder_has_each_family():
    families = {p.parent.name for p in CONFIGS}
    assert {"tum", "replica", "scannet", "synthetic"} <= families


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_shipped_configs_validate(path):
    assert isinstance(load_config(path), Config)


def test_override_and_round_trip(tmp_path):
    cfg = load_config(CONFIGS[0], ["dataset.stride=3", "runtime.seed=7", "dataset.resize=[320, 240]"])
    assert cfg.dataset.stride == 3 and cfg.runtime.seed == 7 and cfg.dataset.resize == (320, 240)
    save_config(cfg, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == cfg


def test_unknown_key_lists_valid_choices(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("dataset: {kind: synthetic}\ntracking: {methd: o3d_odometry}\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert "bad.yaml" in msg and "tracking.methd" in msg and "method" in msg and "depth_max" in msg


def test_bare_yaml_on_off_switches_are_read_as_words(tmp_path):
    """YAML 1.1 reads a bare ``on`` / ``off`` as true / false; a switch spelled that way means the word."""
    cfg = load_config(CONFIGS[0], ["gcgr.per_frame=on"])
    assert cfg.gcgr.per_frame == "on"
    p = tmp_path / "c.yaml"
    p.write_text("dataset: {kind: synthetic}\ngcgr: {per_frame: off}\n")
    assert load_config(p).gcgr.per_frame == "off"
    with pytest.raises(ConfigError, match="gcgr.per_frame"):
        load_config(CONFIGS[0], ["gcgr.per_frame=sometimes"])


def test_unknown_override_key_rejected():
    with pytest.raises(ConfigError, match="unknown key 'dataset.strde'.*stride"):
        config_from_dict(apply_overrides({"dataset": {"kind": "synthetic"}}, ["dataset.strde=2"]))


@pytest.mark.parametrize("data,needle", [
    ({"dataset": {"kind": "tum"}}, "dataset.path is required"),
    ({"dataset": {"kind": "nope", "path": "x"}}, "dataset.kind"),
    ({"dataset": {"kind": "synthetic", "stride": 0}}, "stride"),
    ({"dataset": {"kind": "synthetic", "synthetic": {"n_frames": 1}}}, "n_frames"),
    ({"dataset": {"kind": "synthetic", "synthetic": {"source": "mesh"}}}, "mesh_path"),
    ({"dataset": {"kind": "synthetic"}, "render": {"backend": "opengl"}}, "render.backend"),
    ({"dataset": {"kind": "synthetic"}, "ggf": {"snap": True, "surfel_orientation": "decoder"}}, "surfel_orientation"),
    ({"dataset": {"kind": "synthetic"}, "tracking": {"keyframe_still_rotation_deg": -1}},
     "keyframe_still_rotation_deg"),
    ({}, "dataset"),
])
def test_invalid_values_name_the_field(data, needle):
    with pytest.raises(ConfigError, match=needle):
        config_from_dict(data, "x.yaml")


def test_bad_yaml_and_missing_file(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("dataset: {kind: tum\n  path: [\n")
    with pytest.raises(ConfigError, match="broken.yaml.*not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "none.yaml")
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        apply_overrides({}, ["dataset.stride"])


def test_env_expansion(monkeypatch, tmp_path):
    monkeypatch.setenv("GGFSLAM_DATA", str(tmp_path))
    assert expand_path("${GGFSLAM_DATA}/tum") == tmp_path / "tum"
    monkeypatch.delenv("SURELY_UNSET_VAR", raising=False)
    with pytest.raises(ConfigError, match="SURELY_UNSET_VAR"):
        expand_path("${SURELY_UNSET_VAR}/x")


def test_every_field_is_documented():
    rows = describe_fields()
    undocumented = [key for key, _, doc in rows if not doc.strip()]
    assert not undocumented, undocumented


def test_a_commands_defaults_sit_beneath_the_file_and_the_overrides(tmp_path):
    from ggfslam.config import load_config

    path = tmp_path / "c.yaml"
    path.write_text("name: c\ndataset: {kind: synthetic}\nmapping: {n_offsets: 7}\n")
    defaults = ["mapping.n_offsets=5", "mapping.train_width=320"]
    c = load_config(path, [], defaults=defaults)
    assert (c.mapping.n_offsets, c.mapping.train_width) == (7, 320)  # the file wins over the default
    c = load_config(path, ["mapping.n_offsets=3", "mapping.train_width=160"], defaults=defaults)
    assert (c.mapping.n_offsets, c.mapping.train_width) == (3, 160)  # and --set over both


def test_a_sensor_folder_gets_the_sensor_mapping_schedule_and_overrides_win(tmp_path):
    from ggfslam.config import SENSOR_GGF, SENSOR_MAPPING, folder_config

    tum = tmp_path / "take"
    tum.mkdir()
    (tum / "rgb.txt").write_text("")
    (tum / "depth.txt").write_text("")
    cfg = folder_config(tum)
    assert cfg.dataset.kind == "auto" and cfg.name == "take"
    assert {k: getattr(cfg.mapping, k) for k in SENSOR_MAPPING} == SENSOR_MAPPING
    assert {k: getattr(cfg.ggf, k) for k in SENSOR_GGF} == SENSOR_GGF
    cfg = folder_config(tum, ["mapping.n_offsets=10", "mapping.final_iterations=50", "ggf.surfel_orientation=field"])
    assert cfg.mapping.n_offsets == 10 and cfg.mapping.final_iterations == 50 and cfg.ggf.surfel_orientation == "field"
    assert cfg.mapping.iterations_per_keyframe == SENSOR_MAPPING["iterations_per_keyframe"]
    # rendered Replica (NICE-SLAM layout) keeps the built-in schedule, as does a kind set by hand
    replica = tmp_path / "office0"
    (replica / "results").mkdir(parents=True)
    (replica / "traj.txt").write_text("")
    defaults = Config.model_validate({"dataset": {"path": "x"}}).mapping
    assert folder_config(replica).mapping == defaults
    assert folder_config(replica).ggf.surfel_orientation == "field"
    assert folder_config(tum, ["dataset.kind=replica"]).mapping == defaults
    # a folder no reader knows is named as such
    (tmp_path / "photos").mkdir()
    with pytest.raises(DatasetError, match="cannot tell the dataset format"):
        folder_config(tmp_path / "photos")
