import dataclasses

import pytest

from mgso.config import (Config, ConfigError, apply_overrides, config_to_dict, describe_config, load_config,
                         save_config)


def test_defaults_are_frozen_and_documented():
    cfg = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.window.max_frames = 3  # type: ignore[misc]
    for line in describe_config(cfg):
        assert "#" in line, f"config field without a one-line reason: {line}"


def test_overrides_are_typed():
    cfg = apply_overrides(Config(), ["window.max_frames=5", "runtime.device=cpu", "input.photometric=false"])
    assert cfg.window.max_frames == 5 and cfg.runtime.device == "cpu" and cfg.input.photometric is False
    with pytest.raises(ConfigError, match="expected an integer"):
        apply_overrides(Config(), ["window.max_frames=seven"])
    # PyYAML (YAML 1.1) reads 1e12 without a dot as a string; a float setting takes it as the number
    assert apply_overrides(Config(), ["window.affine_prior_a=1e12"]).window.affine_prior_a == 1e12
    with pytest.raises(ConfigError, match="expected a number"):
        apply_overrides(Config(), ["window.affine_prior_a=lots"])
    with pytest.raises(ConfigError, match="unknown key"):
        apply_overrides(Config(), ["window.max_frame=5"])
    with pytest.raises(ConfigError, match="no section"):
        apply_overrides(Config(), ["nowhere.x=5"])
    with pytest.raises(ConfigError, match="section.key=value"):
        apply_overrides(Config(), ["window"])
    with pytest.raises(ConfigError, match="idepth_fix_prior_marg_fac must be >= 0"):
        apply_overrides(Config(), ["window.idepth_fix_prior_marg_fac=-1"])


def test_profile_inheritance_and_roundtrip(tmp_path):
    parent = tmp_path / "parent.yaml"
    parent.write_text("window:\n  max_frames: 6\nruntime:\n  threads: 1\n")
    child = tmp_path / "child.yaml"
    child.write_text("inherit_from: parent.yaml\nwindow:\n  max_frames: 5\n")
    cfg = load_config(child, ["runtime.seed=3"])
    assert cfg.window.max_frames == 5 and cfg.runtime.threads == 1 and cfg.runtime.seed == 3
    out = tmp_path / "used.yaml"
    save_config(cfg, out)
    assert config_to_dict(load_config(out)) == config_to_dict(cfg)


def test_builtin_profiles_load():
    assert load_config("default") == Config()
    load_config("fast")


def test_bad_profiles_name_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("window: [1, 2\n")
    with pytest.raises(ConfigError, match="bad.yaml.*not valid YAML"):
        load_config(bad)
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("window:\n  maxframes: 3\n")
    with pytest.raises(ConfigError, match="unknown.yaml.*maxframes"):
        load_config(unknown)
    loop = tmp_path / "loop.yaml"
    loop.write_text("inherit_from: loop.yaml\n")
    with pytest.raises(ConfigError, match="cycle"):
        load_config(loop)
    with pytest.raises(ConfigError, match="not found"):
        load_config("no_such_profile")
