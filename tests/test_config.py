import dataclasses
import json
import re

import pytest

from mgso.config import (RECTIFY_FORMS, Config, ConfigError, RuntimeConfig, WindowConfig, apply_overrides,
                         check_runtime, config_to_dict, describe_config, load_config, save_config)


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


def test_mapping_enabled_false_is_refused_not_ignored():
    """mapping.enabled was read by nothing: false still built the map. It is refused with the way to the odometry
    alone; true (what every run's config.yaml holds) still loads."""
    with pytest.raises(ConfigError, match=r"mapping\.enabled must be true \(the odometry alone: mgso run --stage "
                                          r"odometry\), got False"):
        apply_overrides(Config(), ["mapping.enabled=false"])
    assert apply_overrides(Config(), ["mapping.enabled=true"]).mapping.enabled is True


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


@pytest.mark.parametrize("parent", ["3", "[default]", "{a: 1}", "''"])
def test_an_inherit_from_that_is_not_a_name_is_a_one_line_error(tmp_path, parent):
    """Issue 44: a number, list or map here was a TypeError traceback."""
    bad = tmp_path / "bad.yaml"
    bad.write_text(f"inherit_from: {parent}\n")
    with pytest.raises(ConfigError, match="bad.yaml: inherit_from must be a profile name") as err:
        load_config(bad)
    assert "\n" not in str(err.value)
    good = tmp_path / "good.yaml"                   # the control: a name is followed
    good.write_text("inherit_from: fast\n")
    assert load_config(good) == load_config("fast")


def test_a_profile_that_is_not_utf8_is_a_one_line_error(tmp_path):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes("mapping:  # caf\u00e9\n  train:\n    depth_weight: 0.1\n".encode("latin-1"))
    with pytest.raises(ConfigError, match="latin1.yaml: not UTF-8"):
        load_config(bad)
    bad.write_bytes("mapping:  # caf\u00e9\n  train:\n    depth_weight: 0.1\n".encode("utf-8"))
    assert load_config(bad).mapping.train.depth_weight == 0.1


# ------------------------------------------------------------------------------------------ ranges (issue 14)
def _key_pattern(key: str) -> str:
    """The key as a message names it: ``tracking.huber_th`` (range checks) or ``tracking: huber_th`` (the loader's
    type and choice checks)."""
    return r"(\.|: )".join(re.escape(part) for part in key.split("."))


@pytest.mark.parametrize("override", ["runtime.device=tpu", "runtime.threads=-5", "runtime.blas_threads=-1",
                                      "tracking.huber_th=-1"])
def test_settings_that_failed_only_in_tracking_fail_when_the_config_is_built(override):
    """Issue 14, defect 6: these passed load_config and failed only once tracking started, with a traceback."""
    key = override.split("=")[0]
    with pytest.raises(ConfigError, match=_key_pattern(key)) as err:
        load_config(None, [override])
    assert "\n" not in str(err.value) and "got" in str(err.value)


# every numeric or enumerated setting: values just outside its range (all must fail, naming the key)
BAD = {
    "runtime.device": ["tpu", "cuda:x", "gpu0"], "runtime.odometry_device": ["gpu", "cuda:"],
    "runtime.threads": [-1], "runtime.blas_threads": [-1], "runtime.seed": [-1, 2 ** 31],
    "input.start": [-1], "input.end": [-1], "input.stride": [0], "input.width": [-1], "input.height": [-1],
    "input.rectify": ["wide"], "input.on_bad_frame": ["ignore"], "input.fps": [0], "input.prefetch": [-1],
    "input.gt_max_dt": [-0.01],
    "tracking.pyramid_levels": [-1], "tracking.pyramid_max_levels": [0], "tracking.pyramid_min_area": [-1],
    "tracking.pyramid_size_mode": ["stretch"], "tracking.huber_th": [0], "tracking.outlier_th": [0],
    "tracking.outlier_th_sum_component": [0], "tracking.overall_energy_th_weight": [0],
    "tracking.coarse_cutoff_th": [0], "tracking.coarse_flow_stride": [0], "tracking.immature_density": [0],
    "tracking.min_grad_hist_cut": [-0.01, 1.01], "tracking.min_grad_hist_add": [-0.1],
    "tracking.grad_downweight_per_level": [0, 1.01], "tracking.selector_initial_potential": [0],
    "tracking.selector_recursions": [-1], "tracking.max_pix_search": [0, 1.01], "tracking.min_trace_quality": [-0.1],
    "tracking.min_trace_test_radius": [-1], "tracking.trace_stepsize": [0], "tracking.trace_gn_iterations": [-1],
    "tracking.trace_gn_threshold": [-0.1], "tracking.trace_extra_slack_on_th": [0],
    "tracking.trace_slack_interval": [-0.1], "tracking.trace_min_improvement_factor": [-0.1],
    "tracking.coarse_max_iterations": [[], [10, -1]], "tracking.coarse_lambda": [0],
    "tracking.coarse_lambda_extrapolation_limit": [-0.001], "tracking.coarse_min_step": [-0.001],
    "tracking.coarse_saturated_ratio": [-0.01, 1.01], "tracking.coarse_max_cutoff_repeat": [0.99],
    "tracking.coarse_abort_factor": [0.99], "tracking.retrack_threshold": [0],
    "tracking.coarse_rotation_delta": [0, 1.01], "tracking.affine_opt_a": [-0.5, -2], "tracking.affine_opt_b": [-0.5],
    "tracking.kf_global_weight": [-0.1], "tracking.kf_max_shift_t": [-0.01], "tracking.kf_max_shift_r": [-0.01],
    "tracking.kf_max_shift_rt": [-0.01], "tracking.kf_max_affine_weight": [-0.1], "tracking.kf_rmse_factor": [0.99],
    "tracking.kf_max_interval": [-1], "tracking.point_density": [0], "tracking.activation_max_pixel_interval": [0],
    "tracking.min_idepth_h_act": [-1], "tracking.activation_gn_iterations": [-1], "tracking.refine_iterations": [-1],
    "tracking.refine_pose_iterations": [-1], "tracking.refine_affine_iterations": [-1],
    "tracking.init_densities": [[], [0.03, 0]], "tracking.init_max_iterations": [[], [5, -1]],
    "tracking.init_alpha_k": [0], "tracking.init_alpha_w": [-1], "tracking.init_reg_weight": [-0.01, 1.01],
    "tracking.init_coupling_weight": [-0.1], "tracking.init_frames_after_snap": [-1],
    "tracking.init_done_translation": [0], "tracking.init_max_frames": [1], "tracking.init_min_points": [0],
    "tracking.init_max_rmse": [0], "tracking.lost_rmse_factor": [0.99], "tracking.lost_min_rmse": [-0.1],
    "tracking.lost_min_inlier_ratio": [-0.01, 1.01], "tracking.lost_min_inliers": [-1],
    "tracking.lost_max_speed_factor": [0.99], "tracking.lost_speed_window": [0],
    "tracking.realtime_hypothesis_budget_ms": [-1], "tracking.lost_max_translation": [0],
    "window.max_frames": [1, 17], "window.point_capacity": [99], "window.immature_capacity": [99],
    "window.backend": ["joint"], "window.iterations": [0, 101], "window.min_frames": [1, 8],
    "window.affine_prior_a": [-1], "window.affine_prior_b": [-1], "window.idepth_fix_prior": [-1],
    "window.idepth_fix_prior_marg_fac": [-1], "window.marg_weight_fac": [-0.01, 1.01],
    "window.orthogonalize_from": [-1], "window.min_iterations": [-1], "window.th_opt_iterations": [-0.1],
    "window.lambda_init": [0], "window.lambda_min": [-1e-6], "window.lambda_accept": [0, 1.01],
    "window.lambda_reject": [0.99], "window.initial_trans_prior": [-1], "window.initial_rot_prior": [-1],
    "window.initial_aff_a_prior": [-1], "window.initial_aff_b_prior": [-1], "window.frame_energy_th_n": [-0.01, 1.01],
    "window.frame_energy_th_fac_median": [0], "window.frame_energy_th_const_weight": [-0.01, 1.01],
    "window.pairs_per_block": [0], "window.min_points_remaining": [-0.01, 1.01],
    "window.max_log_aff_fac_in_window": [0], "window.min_frame_age": [0], "window.min_good_active_res_for_marg": [0],
    "window.min_good_res_for_marg": [0], "window.min_idepth_h_marg": [-1],
    "mapping.capacity": [0], "mapping.sh_degree": [-1, 4], "mapping.lambda_dssim": [-0.01, 1.01],
    "mapping.scene_extent_margin": [0],
    "mapping.optim.lr_means_init": [-1e-6], "mapping.optim.lr_means_final": [-1e-6],
    "mapping.optim.lr_means_max_steps": [-1], "mapping.optim.lr_means_delay_steps": [-1],
    "mapping.optim.lr_means_delay_mult": [-0.01, 1.01], "mapping.optim.lr_log_scales": [-1e-6],
    "mapping.optim.lr_quats": [-1e-6], "mapping.optim.lr_opacity": [-1e-6], "mapping.optim.lr_sh_dc": [-1e-6],
    "mapping.optim.lr_sh_rest": [-1e-6], "mapping.optim.beta1": [-0.01, 1.0], "mapping.optim.beta2": [1.0],
    "mapping.optim.eps": [0], "mapping.optim.bias_correction": ["adamw"], "mapping.optim.lr_exposure_init": [-1e-6],
    "mapping.optim.lr_exposure_final": [-1e-6],
    "mapping.densify.refine_start_step": [-1], "mapping.densify.refine_stop_step": [-1],
    "mapping.densify.refine_every": [0], "mapping.densify.reset_every": [-1],
    "mapping.densify.reset_opacity_value": [0, 1], "mapping.densify.pause_refine_after_reset": [-1],
    "mapping.densify.grad_mode": ["abs"], "mapping.densify.grow_grad2d": [0], "mapping.densify.grow_grad2d_abs": [0],
    "mapping.densify.absgs_split_grad2d": [0], "mapping.densify.percent_dense": [-0.01],
    "mapping.densify.split_children": [1], "mapping.densify.split_scale_factor": [0],
    "mapping.densify.grow_min_views": [-1], "mapping.densify.prune_opacity": [-0.01, 1],
    "mapping.densify.prune_scale3d": [0], "mapping.densify.prune_screen_px": [-1],
    "mapping.densify.max_aspect": [0.5, -1], "mapping.densify.prune_min_age": [-1],
    "mapping.densify.prune_weight_px": [-0.1], "mapping.densify.prune_weight_views": [0],
    "mapping.train.iterations": [-1], "mapping.train.background": [[1.5, 0, 0], [0, -0.1, 0]],
    "mapping.train.min_scene_extent": [0], "mapping.train.pyramid_levels": [0], "mapping.train.pyramid_uses": [-1],
    "mapping.train.sh_degree_interval": [-1], "mapping.train.depth_weight": [-0.1],
    "mapping.train.lr_pose_translation": [-1e-6], "mapping.train.lr_pose_rotation": [-1e-6],
    "mapping.train.metrics_every": [-1], "mapping.train.init_points": [0],
    "mapping.train.init_depth_range": [[2, 1], [0, 1]], "mapping.train.init_max_screen_px": [-1],
    "mapping.train.init_opacity": [0, 1], "mapping.train.init_knn": [0], "mapping.train.holdout_every": [-1],
    "mapping.train.max_train_views": [-1],
    "mapping.seeding.min_point_weight": [-0.1], "mapping.seeding.fill_min_triangle_area_px": [-1],
    "mapping.seeding.fill_depth": ["median"], "mapping.seeding.fill_max_depth_ratio": [0.99],
    "mapping.seeding.fill_area_per_point_px": [0], "mapping.seeding.fill_max_subdivisions": [0],
    "mapping.seeding.visibility_threshold": [0, 1.01], "mapping.seeding.depth_tolerance": [-0.1],
    "mapping.seeding.alpha_downscale": [0], "mapping.seeding.coverage_stop": [-0.01, 0.6],
    "mapping.seeding.max_depth_factor": [-1, 0.5], "mapping.seeding.depth_rule_max_median": [-0.1],
    "mapping.seeding.distrust_median": [-1],
    "mapping.seeding.min_new_gaussians": [-1],
    "mapping.seeding.init_opacity": [0, 1], "mapping.seeding.knn": [0], "mapping.seeding.scale_min_px": [0],
    "mapping.seeding.scale_max_px": [0.4],
    "mapping.mapper.iterations_per_keyframe": [-1], "mapping.mapper.final_iterations": [-1],
    "mapping.mapper.queue_size": [0], "mapping.mapper.newest_probability": [-0.01, 1.01],
    "mapping.mapper.loss_share": [-0.01, 1.01],
    "mapping.mapper.init": ["grid"], "mapping.mapper.min_train_views": [0], "mapping.mapper.exposure": ["auto"],
    "mapping.mapper.refine_every": [-1], "mapping.mapper.running_max_pixels": [-1],
    "mapping.mapper.final_refine_after": [-1], "mapping.mapper.final_coarse_share": [-0.1, 1.5],
    "mapping.mapper.final_coarser_share": [-0.1, 1.5],
    "mapping.mapper.defer_seeding_above": [-1], "mapping.mapper.final_budget_s": [-1.0],
    "mapping.mapper.running_train_share": [-0.1, 1.0], "mapping.mapper.prune_opacity": [-0.1, 1],
    "mapping.mapper.sampler": ["newest"], "mapping.mapper.grow_grad2d": [-0.001],
    "mapping.mapper.prune_weight_px": [-0.1],
    "mapping.train.refine_poses": ["sometimes", 2],
    "output.trajectory_format": ["euroc"],
    "system.mode": ["fast"], "system.playback_speed": [-0.1],
    "system.odometry_threads": [-1], "system.mapper_threads": [-1], "system.mapper_nice": [-1, 20],
    "system.image_slots": [0], "system.mapper_lead": [-1],
    "system.max_lag_ms": [-1.0],
    "input.live_timeout_s": [0, 3601], "input.live_max_frames": [-1], "input.live_duration_s": [-0.1],
    "loop.orb_features": [0], "loop.depth_radius_px": [0], "loop.min_keyframe_gap": [-1],
    "loop.max_candidates": [0], "loop.proximity_depths": [-0.1], "loop.min_matches": [-1], "loop.geometry": ["old"],
    "loop.match_ratio": [0, 1.01], "loop.ransac_iterations": [0], "loop.inlier_px": [0], "loop.min_inliers": [2],
    "loop.min_pnp_inliers": [3],
    "loop.max_photometric_rmse": [0], "loop.min_photometric_inliers": [0, 1.1], "loop.odometry_neighbours": [0],
    "loop.loop_edge_weight": [0], "loop.graph_iterations": [0],
    "loop.prefilter_above": [-1], "loop.prefilter_keep": [0], "loop.vocabulary_words": [0],
    "loop.realtime_cpu_share": [0, 1.1], "loop.depth_tolerance": [0], "loop.min_depth_consistent": [-0.1, 1.1], "loop.min_depth_compared": [-1],
    "loop.planar_fraction": [-0.1, 1.1],
}
FREE = {"input.camera"}  # names a camera of the dataset's layout: checked when the sequence is opened


def _leaves(cfg, prefix=""):
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            yield from _leaves(v, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", v


def test_every_numeric_or_enumerated_setting_has_a_range_in_the_table():
    leaves = dict(_leaves(Config()))
    want = {k for k, v in leaves.items() if not isinstance(v, bool)} - FREE
    assert want == set(BAD), (sorted(want - set(BAD)), sorted(set(BAD) - want))


@pytest.mark.parametrize("key", sorted(BAD))
def test_each_setting_fails_just_outside_its_range_and_passes_at_its_default(key):
    default = dict(_leaves(Config()))[key]
    cfg = load_config(None, [f"{key}={json.dumps(list(default) if isinstance(default, tuple) else default)}"])
    assert dict(_leaves(cfg))[key] == default
    for bad in BAD[key]:
        with pytest.raises(ConfigError, match=_key_pattern(key)) as err:
            load_config(None, [f"{key}={json.dumps(bad)}"])
        assert "\n" not in str(err.value)


def test_numbers_must_be_finite():
    for override in ("tracking.huber_th=.nan", "window.lambda_init=.inf", "mapping.optim.eps=.nan",
                     "mapping.train.background=[0, .nan, 0]", "tracking.init_densities=[.inf]"):
        with pytest.raises(ConfigError, match="must be a finite number"):
            load_config(None, [override])


def test_problems_are_collected_into_one_line_naming_the_file(tmp_path):
    bad = tmp_path / "ranges.yaml"
    bad.write_text("tracking:\n  huber_th: -1\n  coarse_lambda: 0\nwindow:\n  min_frames: 9\n"
                   "input:\n  start: 5\n  end: 5\n")
    with pytest.raises(ConfigError) as err:
        load_config(bad)
    msg = str(err.value)
    assert msg.startswith(str(bad)) and "\n" not in msg
    for part in ("tracking.huber_th must be > 0, got -1.0", "tracking.coarse_lambda must be > 0, got 0.0",
                 "window.min_frames must be in [2, 7], got 9", "input.end must be 0 (to the end) or > start (5)"):
        assert part in msg, msg
    # the sections themselves check, whoever builds them
    with pytest.raises(ConfigError, match="window.lambda_accept"):
        WindowConfig(lambda_accept=0.0)


def test_rectify_choices_are_the_cameras():
    from mgso.camera import RECTIFY_MODES

    assert set(RECTIFY_FORMS) == set(RECTIFY_MODES) | {""}


# ------------------------------------------------------------------------------ devices (check_runtime)
def _with_devices(device="auto", odometry_device=""):
    return load_config(None, [f"runtime.device={device}", f"runtime.odometry_device='{odometry_device}'"])


def test_device_forms_are_checked_at_build():
    for name in ("cpu", "CPU", "auto", "cuda", "Cuda:0", "cuda:12"):
        assert _with_devices(name).runtime.device == name
    assert Config(RuntimeConfig(device=" auto ")).runtime.device == " auto "  # as runtime.resolve_device: stripped
    assert _with_devices("cpu", "cuda:1").runtime.odometry_device == "cuda:1"


def test_check_runtime_costs_nothing_for_cpu_and_auto(monkeypatch):
    from mgso_kernels import runtime

    def no(*_):
        raise AssertionError("Warp asked about CUDA for a cpu/auto configuration")

    monkeypatch.setattr(runtime, "cuda_device_count", no)
    for device, odo in (("cpu", ""), ("auto", ""), ("AUTO", "cpu"), ("cpu", "auto")):
        check_runtime(_with_devices(device, odo))
    with pytest.raises(AssertionError):  # the control: a cuda name does ask
        check_runtime(_with_devices("cuda"))


def test_check_runtime_without_cuda(monkeypatch):
    """Warp's CUDA absent (as on this project's CPU machine): a cuda device is a one-line ConfigError naming the
    setting; cpu and auto pass."""
    import warp as wp

    monkeypatch.setattr(wp, "is_cuda_available", lambda: False)
    for device, odo, key in (("cuda", "", "runtime.device"), ("CUDA:0", "", "runtime.device"),
                             ("cpu", "cuda", "runtime.odometry_device"), ("auto", "cuda:1", "runtime.odometry_device")):
        with pytest.raises(ConfigError, match=re.escape(key) + ".*no CUDA device") as err:
            check_runtime(_with_devices(device, odo))
        assert "\n" not in str(err.value)
    check_runtime(_with_devices("cpu"))
    check_runtime(_with_devices("auto", "cpu"))


def test_check_runtime_counts_the_devices(monkeypatch):
    from mgso_kernels import runtime

    monkeypatch.setattr(runtime, "cuda_device_count", lambda: 1)
    check_runtime(_with_devices("cuda:0", "cuda"))
    with pytest.raises(ConfigError, match=r"runtime.device is 'cuda:1', but this machine has 1 CUDA device\(s\)"):
        check_runtime(_with_devices("cuda:1"))


def test_check_runtime_on_this_machine():
    """No monkeypatch: on a machine without a GPU, cuda fails (skipped where one is present)."""
    from mgso_kernels import runtime

    if runtime.cuda_device_count() > 0:
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(ConfigError, match="runtime.device is 'cuda', but Warp sees no CUDA device"):
        check_runtime(_with_devices("cuda"))
    check_runtime(_with_devices("auto"))
