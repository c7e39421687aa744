"""Typed configuration: frozen dataclasses, one section per subsystem, every default with a one-line reason.

- Defaults live here (``opt(default, "reason")``); the reason is kept in the field's metadata so that
  ``mgso info --config`` can print it.
- YAML profiles (``mgso/configs/*.yaml`` or any file) give a nested mapping of the fields they change and may name a
  parent with ``inherit_from: <profile name or path>`` (as MonoGS does).
- Dotted overrides from the command line: ``--set tracking.max_frames=7`` (value parsed as YAML, then checked
  against the field's type).

Unknown keys, wrong types and values outside a setting's range are errors that name the file (or override), the key,
the value and what is allowed; nothing is silently ignored. Each section checks every one of its numbers and choices
when it is built (``__post_init__``: all problems of a file in one line), so ``mgso info`` and ``--stage check`` catch
them before any work starts; whether a named CUDA device exists needs Warp and is :func:`check_runtime`'s job.
Subsystems read their own section and get it as an argument; nothing reads global configuration.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping, Sequence

import yaml

__all__ = [
    "opt", "RuntimeConfig", "InputConfig", "TrackingConfig", "WindowConfig", "MappingConfig", "OptimConfig",
    "DensifyConfig", "TrainConfig", "SeedingConfig", "MapperConfig", "OutputConfig", "SystemConfig", "LoopConfig",
    "Config", "ConfigError", "load_config", "apply_overrides", "config_from_dict", "config_to_dict", "save_config",
    "describe_config", "PROFILE_DIR", "available_profiles", "check_runtime", "DEVICE_FORMS", "RECTIFY_FORMS",
    "TRAJECTORY_FORMATS",
]

PROFILE_DIR = Path(__file__).resolve().parent / "configs"


class ConfigError(ValueError):
    """A configuration file or override is wrong; the message names where and what."""


def opt(default: Any, reason: str) -> Any:
    """A dataclass field with a default and its one-line reason."""
    if isinstance(default, (list, dict, set)):
        raise TypeError("use tuples for sequence defaults so the config stays immutable")
    return field(default=default, metadata={"reason": reason})


DEVICE_FORMS = "cpu, cuda, cuda:N or auto (any case)"
_DEVICE_RE = re.compile(r"cpu|auto|cuda(:[0-9]+)?")
RECTIFY_FORMS = ("", "keep", "crop", "full", "none")  # mgso.camera.RECTIFY_MODES or empty (a test compares)
TRAJECTORY_FORMATS = ("tum", "kitti")
_SEED_MAX = 2 ** 31 - 1  # the seed also reaches Warp kernels as an int32 (mgso_kernels.trace.TraceParams.seed)


class _RangeError(ConfigError):
    """A value outside its range, found by a section's ``__post_init__`` (the loader adds the file or override)."""


class _Checks:
    """The range checks of one section. Every number must be finite (NaN fails every range; no setting means
    anything by infinity); each failed rule adds ``section.key must be <allowed>, got <value>``, and :meth:`done`
    raises them all as one line, so that a file with several mistakes is fixed in one go."""

    def __init__(self, section: str, obj: Any):
        self.section, self.obj = section, obj
        self.problems: list[str] = []
        self._bad: set[str] = set()
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if any(isinstance(x, float) and not math.isfinite(x) for x in (v if isinstance(v, tuple) else (v,))):
                self.rule(False, f.name, "a finite number")

    def rule(self, ok: bool, name: str, allowed: str) -> None:
        if not ok and name not in self._bad:
            self._bad.add(name)
            self.problems.append(f"{self.section}.{name} must be {allowed}, got {getattr(self.obj, name)!r}")

    def ge(self, lo: float, *names: str) -> None:
        for n in names:
            self.rule(getattr(self.obj, n) >= lo, n, f">= {lo}")

    def gt(self, lo: float, *names: str) -> None:
        for n in names:
            self.rule(getattr(self.obj, n) > lo, n, f"> {lo}")

    def within(self, lo: float, hi: float, *names: str, open_lo: bool = False, open_hi: bool = False) -> None:
        for n in names:
            v = getattr(self.obj, n)
            ok = (v > lo if open_lo else v >= lo) and (v < hi if open_hi else v <= hi)
            self.rule(ok, n, f"in {'(' if open_lo else '['}{lo}, {hi}{')' if open_hi else ']'}")

    def one_of(self, options: Sequence[str], *names: str) -> None:
        for n in names:
            self.rule(getattr(self.obj, n) in options, n, "one of " + ", ".join(repr(o) for o in options))

    def each(self, name: str, lo: float, strict: bool = False) -> None:
        """A non-empty tuple whose every value is ``>= lo`` (``> lo`` when strict)."""
        v = getattr(self.obj, name)
        ok = len(v) > 0 and all((x > lo) if strict else (x >= lo) for x in v)
        self.rule(ok, name, f"a non-empty list of numbers {'>' if strict else '>='} {lo}")

    def done(self) -> None:
        if self.problems:
            raise _RangeError("; ".join(self.problems))


def _device_form_ok(name: str) -> bool:
    return bool(_DEVICE_RE.fullmatch(name.strip().lower()))


# --------------------------------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class RuntimeConfig:
    device: str = opt("auto", "Warp device: cpu, cuda, cuda:N, or auto (CUDA when present, else CPU)")
    threads: int = opt(0, "CPU threads for split kernel launches; 0 = all available cores")
    blas_threads: int = opt(1, "threads of NumPy's BLAS (small host matrices; more threads spin against the kernel "
                               "workers); 0 = all cores")
    odometry_device: str = opt("", "Warp device of the odometry's kernels when it should differ from `device` (e.g. "
                                   "cpu odometry beside a cuda map: the two threads then share no CUDA stream); "
                                   "empty = `device`")
    seed: int = opt(0, "seed of every random choice (pixel selection directions, random init), for repeatable runs")

    def __post_init__(self):
        c = _Checks("runtime", self)
        c.rule(_device_form_ok(self.device), "device", DEVICE_FORMS)
        c.rule(self.odometry_device == "" or _device_form_ok(self.odometry_device), "odometry_device",
               f"empty (= device) or {DEVICE_FORMS}")
        c.ge(0, "threads", "blas_threads")
        c.within(0, _SEED_MAX, "seed")
        c.done()


@dataclass(frozen=True)
class InputConfig:
    """Reading frames (mgso.io): which frames, which camera, how to undistort (docs/datasets.md)."""

    start: int = opt(0, "first frame index used from the sequence")
    end: int = opt(0, "one past the last frame index used; 0 = to the end")
    stride: int = opt(1, "use every n-th frame (1 = every frame)")
    width: int = opt(0, "output (undistorted) image width; 0 = the calibration's output size")
    height: int = opt(0, "output (undistorted) image height; 0 = the calibration's output size")
    photometric: bool = opt(True, "apply photometric calibration (response, vignette, exposure) when present")
    rectify: str = opt("", "undistortion output: keep (nearly the whole field of view; the few pixels without a "
                           "source lie in the outer 3 rows/columns, marked invalid), crop (DSO's: no pixel without a "
                           "source, fr1 loses 26 %), full (whole input visible), none (input intrinsics); empty = "
                           "what the calibration file says (keep for a distorted lens if silent)")
    camera: str = opt("", "camera of a multi-camera layout (EuRoC cam0/cam1, KITTI image_0/image_2); empty = the "
                          "layout's first camera")
    fps: float = opt(30.0, "frame rate for timestamps when a layout has none (image folders without times.txt, "
                           "Replica)")
    prefetch: int = opt(2, "frames decoded ahead by a background thread while iterating (PNG decoding is a large "
                           "share of a frame's time); 0 = decode in the caller")
    gt_max_dt: float = opt(0.02, "largest time difference (s) when matching ground-truth poses to frames (TUM "
                                 "RGB-D, EuRoC, TUM monoVO: nearest pose within this)")
    on_bad_frame: Literal["skip", "stop"] = opt("skip", "a frame that cannot be read (truncated or corrupt file, "
                                                        "wrong size): skip it with a warning, counted in metrics.json "
                                                        "and frames.csv, or stop the run (the outputs of the frames "
                                                        "before it are written either way)")
    live_timeout_s: float = opt(5.0, "live camera or stream (docs/live.md): a source that delivers no frame for this "
                                     "many seconds (unplugged, network gone) ends the run as at the end of the input, "
                                     "with a warning, outputs written")
    live_max_frames: int = opt(0, "live camera or stream: end the run after this many frames captured (mgso run "
                                  "--max-frames); 0 = no limit")
    live_duration_s: float = opt(0.0, "live camera or stream: end the run after this many seconds of frames (mgso "
                                      "run --duration); 0 = no limit")

    def __post_init__(self):
        c = _Checks("input", self)
        c.ge(0, "start", "end", "width", "height", "prefetch", "gt_max_dt")
        c.within(0.1, 3600.0, "live_timeout_s")
        c.ge(0, "live_max_frames", "live_duration_s")
        c.rule(self.end == 0 or self.end > self.start, "end", f"0 (to the end) or > start ({self.start})")
        c.ge(1, "stride")
        c.gt(0, "fps")
        c.one_of(RECTIFY_FORMS, "rectify")
        c.one_of(("skip", "stop"), "on_bad_frame")
        c.done()


@dataclass(frozen=True)
class TrackingConfig:
    """DSO front end: pyramid, photometric residual, coarse tracking, pixel selection, epipolar search.

    Defaults are DSO's (``src/util/settings.cpp``); the name in parentheses is DSO's setting.
    """

    # image pyramid
    pyramid_levels: int = opt(0, "pyramid levels; 0 = automatic: halve while the level has > pyramid_min_area "
                                 "pixels, at most pyramid_max_levels (DSO setGlobalCalib: 640x480 -> 4, KITTI -> 5)")
    pyramid_max_levels: int = opt(6, "upper bound on automatic pyramid levels (DSO PYR_LEVELS = 6)")
    pyramid_min_area: int = opt(5000, "automatic levels stop once a level has <= this many pixels (DSO: 5000); "
                                      "1200 gives 640x480 a 40x30 coarsest level")
    pyramid_size_mode: str = opt("crop", "sizes not divisible by 2^(levels-1): 'crop' centrally or 'pad' by edge "
                                         "replication; the principal point is shifted to match either way")
    # photometric residual
    huber_th: float = opt(9.0, "Huber threshold on the photometric residual, intensity units (setting_huberTH)")
    outlier_th: float = opt(144.0, "energy threshold per pattern pixel, 12^2; a new point's trace fails above "
                                   "8 x this (setting_outlierTH)")
    outlier_th_sum_component: float = opt(2500.0, "c^2 of the gradient weight sqrt(c^2/(c^2+|grad I|^2)); higher = "
                                                  "weaker down-weighting of strong gradients "
                                                  "(setting_outlierTHSumComponent = 50^2)")
    overall_energy_th_weight: float = opt(1.0, "scales the energy thresholds; squared "
                                               "(setting_overallEnergyTHWeight)")
    # coarse tracking
    coarse_cutoff_th: float = opt(20.0, "coarse tracker: residuals above this count with a constant energy and "
                                        "stay out of the system; doubled while > 60% saturate "
                                        "(setting_coarseCutoffTH)")
    coarse_flow_stride: int = opt(32, "flow indicators for the keyframe decision from every n-th reference point "
                                      "(DSO calcRes: i % 32 at level 0)")
    coarse_pattern: bool = opt(False, "coarse tracker uses the 8-pixel pattern per point instead of one residual "
                                      "per depth-map pixel (DSO: one residual per pixel)")
    # pixel selection
    immature_density: float = opt(1500.0, "candidate points selected per new keyframe "
                                          "(setting_desiredImmatureDensity)")
    min_grad_hist_cut: float = opt(0.5, "block threshold = this quantile of the block's gradient histogram ... "
                                        "(setting_minGradHistCut, the median)")
    min_grad_hist_add: float = opt(7.0, "... plus this many gradient units (setting_minGradHistAdd)")
    grad_downweight_per_level: float = opt(0.75, "threshold factor per coarser selection level "
                                                 "(setting_gradDownweightPerLevel)")
    select_direction_distribution: bool = opt(True, "pick the pixel whose gradient projects most onto a random "
                                                    "direction per cell, spreading gradient directions "
                                                    "(setting_selectDirectionDistribution)")
    selector_initial_potential: int = opt(3, "starting cell size of the selector in pixels; adapts to the density "
                                             "(PixelSelector currentPotential = 3)")
    selector_recursions: int = opt(1, "re-selections allowed per keyframe to approach the density "
                                      "(makeMaps recursionsLeft = 1)")
    # epipolar search of immature points
    max_pix_search: float = opt(0.027, "longest epipolar segment searched, as a fraction of width + height "
                                       "(setting_maxPixSearch)")
    min_trace_quality: float = opt(3.0, "second-best / best energy a traced point needs to be activated "
                                        "(setting_minTraceQuality)")
    min_trace_test_radius: int = opt(2, "steps around the best match excluded when looking for the second best "
                                        "(setting_minTraceTestRadius)")
    trace_stepsize: float = opt(1.0, "pixel step of the discrete epipolar search (setting_trace_stepsize)")
    trace_gn_iterations: int = opt(3, "Gauss-Newton refinements along the line (setting_trace_GNIterations)")
    trace_gn_threshold: float = opt(0.1, "stop refining below this step in pixels (setting_trace_GNThreshold)")
    trace_extra_slack_on_th: float = opt(1.2, "energy outlier test is relaxed by this factor "
                                              "(setting_trace_extraSlackOnTH)")
    trace_slack_interval: float = opt(1.5, "skip tracing when the interval projects shorter than this, pixels "
                                           "(setting_trace_slackInterval)")
    trace_min_improvement_factor: float = opt(2.0, "skip tracing when the error bound would not shrink the "
                                                   "interval by this factor (setting_trace_minImprovementFactor)")

    # coarse tracker (DSO CoarseTracker::trackNewestCoarse, FullSystem::trackNewCoarse)
    coarse_max_iterations: tuple[int, ...] = opt((10, 20, 50, 50, 50, 50), "Levenberg-Marquardt iterations per "
                                                 "pyramid level, finest first (trackNewestCoarse maxIterations)")
    coarse_lambda: float = opt(0.01, "initial Levenberg-Marquardt damping of each level (trackNewestCoarse)")
    coarse_lambda_extrapolation_limit: float = opt(0.001, "below this damping the step is extrapolated by "
                                                          "(limit/lambda)^(1/4) (lambdaExtrapolationLimit)")
    coarse_min_step: float = opt(1e-3, "a level stops when the scaled step is shorter than this (inc.norm())")
    coarse_saturated_ratio: float = opt(0.6, "the cutoff doubles while more than this share of residuals "
                                             "saturates, and the level is repeated once (trackNewestCoarse)")
    coarse_max_cutoff_repeat: float = opt(50.0, "largest cutoff multiplier (levelCutoffRepeat < 50)")
    coarse_abort_factor: float = opt(1.5, "a motion hypothesis is abandoned on a level whose RMSE exceeds this x "
                                          "the best so far (trackNewestCoarse minResForAbort)")
    skip_duplicate_frames: bool = opt(True, "a frame whose image is identical to the previous one (a repeated "
                                            "frame, common from webcams and some recordings) takes the previous "
                                            "frame's pose instead of being tracked: its RMSE of 0 against a keyframe "
                                            "would otherwise become DSO's baseline (then every motion hypothesis is "
                                            "tried on the next frame and it always becomes a keyframe)")
    retrack_threshold: float = opt(1.5, "try the next motion hypothesis until the RMSE is below this x the last "
                                        "frame's (setting_reTrackThreshold)")
    realtime_hypothesis_budget_ms: float = opt(33.0, "real time only (--realtime, live sources): once a motion "
                                                     "hypothesis has tracked well, stop trying the others after "
                                                     "this many ms of the frame, even above retrack_threshold (DSO "
                                                     "tries all 31 then: 350-470 ms at 320x240, and the frames "
                                                     "behind are dropped; docs/tracking.md); 0 = DSO's rule always")
    realtime_current_keyframe_requests: bool = opt(True, "real time only (the odometry's mapping thread): a "
                                                         "keyframe request counts only if the frame was tracked "
                                                         "against the newest keyframe (DSO needNewKFAfter): the "
                                                         "frames tracked while the thread makes a keyframe, against "
                                                         "the one before, would each ask again (docs/tracking.md)")
    coarse_rotation_hypotheses: bool = opt(True, "after constant/double/half/zero motion also try 26 small "
                                                 "rotations of the constant-motion guess (trackNewCoarse)")
    coarse_rotation_delta: float = opt(0.02, "quaternion component of those rotations, about 2.3 degrees "
                                             "(rotDelta)")
    affine_opt_a: float = opt(0.0, "affine brightness a: -1 fixes it, >= 0 estimates it (a > 0 is the window's "
                                   "prior weight). DSO setting_affineOptModeA; mgso defaults to DSO mode=1 (no "
                                   "photometric calibration, a and b free); DSO mode=0 uses 1e12")
    affine_opt_b: float = opt(0.0, "as affine_opt_a for the offset b (setting_affineOptModeB; DSO mode=0: 1e8)")
    affine_fixed_with_exposure: bool = opt(False, "fix a and b (DSO mode=2, 'perfect images') whenever both frames "
                                                  "carry exposure times; otherwise affine_opt_a/b decide")
    # keyframe decision (DSO FullSystem::addActiveFrame)
    kf_global_weight: float = opt(1.0, "scales all keyframe thresholds; 2 = about twice as many keyframes "
                                       "(setting_kfGlobalWeight)")
    kf_max_shift_t: float = opt(0.04, "weight of the translation-only mean flow, as DSO: x (640+480) / (w+h) "
                                      "(setting_maxShiftWeightT = 0.04 (640+480))")
    kf_max_shift_r: float = opt(0.0, "weight of the rotation-only flow; DSO does not compute it "
                                     "(setting_maxShiftWeightR = 0)")
    kf_max_shift_rt: float = opt(0.02, "weight of the full (rotation and translation) mean flow "
                                       "(setting_maxShiftWeightRT = 0.02 (640+480))")
    kf_max_affine_weight: float = opt(2.0, "weight of |log a_rel|, the brightness change to the reference "
                                           "(setting_maxAffineWeight)")
    kf_rmse_factor: float = opt(2.0, "new keyframe when the tracking RMSE exceeds this x the first RMSE against "
                                     "the reference (DSO: 2 * firstCoarseRMSE)")
    kf_max_interval: int = opt(0, "new keyframe at the latest after this many frames since the last one; 0 = no "
                                  "limit (DSO has none)")
    # point activation (DSO FullSystem::activatePointsMT, optimizeImmaturePoint)
    point_density: float = opt(2000.0, "active points aimed at in the window; the activation distance adapts "
                                       "(setting_desiredPointDensity)")
    activation_max_pixel_interval: float = opt(8.0, "a traced point may activate when its last interval is "
                                                    "shorter than this, pixels (lastTracePixelInterval < 8)")
    min_idepth_h_act: float = opt(100.0, "an activated point needs this much inverse-depth Hessian "
                                         "(setting_minIdepthH_act)")
    activation_gn_iterations: int = opt(3, "Gauss-Newton steps on a new point's inverse depth "
                                           "(setting_GNItsOnPointActivation)")
    # fixed-window depth refinement (the stand-in for the window bundle adjustment)
    refine_iterations: int = opt(3, "Gauss-Newton steps on the active points' inverse depths after each "
                                    "keyframe, poses fixed (until the window optimisation replaces it)")
    refine_pose: bool = opt(False, "also refine the newest keyframe's pose against the points after the depths")
    refine_pose_iterations: int = opt(5, "Gauss-Newton steps of that pose refinement (a step is kept only when the "
                                         "energy drops)")
    refine_affine: bool = opt(True, "the fixed back end also estimates every keyframe's affine brightness but the "
                                    "oldest's over the window's residuals in both directions, so that the tracker's "
                                    "brightness bias (bilinear sampling lowers contrast) cancels instead of adding up "
                                    "from keyframe to keyframe")
    refine_affine_iterations: int = opt(2, "Gauss-Newton steps of that affine estimate")
    # monocular initialisation (DSO CoarseInitializer)
    init_densities: tuple[float, ...] = opt((0.03, 0.05, 0.15, 0.5, 1.0), "points of the first frame per level "
                                            "as a fraction of w*h at level 0 (CoarseInitializer::setFirst)")
    init_max_iterations: tuple[int, ...] = opt((5, 5, 10, 30, 50, 50), "iterations per level, finest first "
                                               "(CoarseInitializer::trackFrame maxIterations)")
    init_alpha_k: float = opt(2.5 ** 2, "regulariser energy cap per point: above it the scale is free "
                                        "(alphaK = 2.5^2)")
    init_alpha_w: float = opt(150.0 ** 2, "weight pulling inverse depths to 1 and translation to 0 before enough "
                                          "parallax (alphaW = 150^2)")
    init_reg_weight: float = opt(0.8, "weight of the neighbours' median inverse depth in the smoothed depth "
                                      "(regWeight)")
    init_coupling_weight: float = opt(1.0, "weight coupling each inverse depth to its smoothed value after "
                                           "snapping (couplingWeight)")
    init_frames_after_snap: int = opt(5, "frames of the camera after enough parallax before initialising "
                                         "(trackFrame: frameID > snappedAt + 5; the frames dropped in real time "
                                         "count)")
    init_done_translation: float = opt(0.1, "the initialisation also ends, before init_frames_after_snap, once the "
                                            "translation reaches this (scene units: mean inverse depth 1), so fast "
                                            "motion (a car) does not lose the overlap; handheld motion rarely gets "
                                            "there first (mgso; DSO only counts frames)")
    init_max_frames: int = opt(40, "give up an initialisation attempt after this many frames of the camera "
                                   "without enough parallax and retry from a newer first frame (DSO waits forever)")
    init_min_points: int = opt(50, "a first frame with fewer selected points (level 0) is not used")
    init_max_rmse: float = opt(25.0, "give up an initialisation attempt when the level-0 RMSE exceeds this (the "
                                     "first frame does not match the others: a frame of noise gives 30-35; KITTI "
                                     "initialises at 14-17; DSO resets when the first window's RMSE exceeds 20)")
    # tracking loss
    lost_rmse_factor: float = opt(3.0, "tracking is lost when the RMSE exceeds this x the reference's first RMSE "
                                       "(DSO only detects non-finite results)")
    lost_min_rmse: float = opt(6.0, "... but never below this RMSE (intensity units), so a very clean reference "
                                    "does not make small residuals a loss")
    lost_min_inlier_ratio: float = opt(0.25, "tracking is lost when fewer than this share of the reference's "
                                             "level-0 points that project into the frame are within the cutoff "
                                             "(points the frame has turned away from are no loss: a fast-turning "
                                             "camera sees few of its reference's points and fits them; until "
                                             "2026-12-06 a share of all the reference's points, docs/tracking.md)")
    lost_min_inliers: int = opt(30, "tracking is lost when fewer level-0 residuals than this are inliers (a map "
                                    "that has lost its points leaves the pose unconstrained however small the RMSE; "
                                    "100 until 2026-12-06, which lost freiburg1_rpy's frames against keyframes that "
                                    "the turning camera had left with 30-100 points, all fitting: docs/tracking.md)")
    lost_max_speed_factor: float = opt(10.0, "tracking is lost when a frame moves more than this x the segment's "
                                             "recent median motion per frame (at least 1 % of the reference's median "
                                             "depth), after 5 tracked frames: a sudden jump of the estimate, not of "
                                             "the camera")
    lost_speed_window: int = opt(30, "the tracked frames whose median motion is the speed check's typical motion "
                                     "(recent, so that a camera that speeds up, or a scale that drifts, moves it)")
    lost_max_translation: float = opt(2.0, "tracking is lost when the frame is farther from its reference keyframe "
                                           "than this x the median depth (the reference's, or the segment's first "
                                           "points' when smaller: a map drifted towards infinity leaves the "
                                           "translation free to run away)")

    def __post_init__(self):
        c = _Checks("tracking", self)
        # pyramid (mgso_kernels.image.plan_pyramid)
        c.ge(0, "pyramid_levels", "pyramid_min_area")
        c.ge(1, "pyramid_max_levels")
        c.one_of(("crop", "pad"), "pyramid_size_mode")
        # residual: the Huber weight divides by huber_th, the gradient weight by c^2 (+ |grad|^2); the energy
        # thresholds are products of the weight (squared) and outlier_th
        c.gt(0, "huber_th", "outlier_th", "outlier_th_sum_component", "overall_energy_th_weight", "coarse_cutoff_th")
        c.ge(1, "coarse_flow_stride")  # i % stride
        # pixel selection (mgso.tracking.pixel_selector)
        c.gt(0, "immature_density", "point_density")
        c.within(0, 1, "min_grad_hist_cut")  # a quantile
        c.ge(0, "min_grad_hist_add")
        c.within(0, 1, "grad_downweight_per_level", open_lo=True)  # a factor per coarser level, down
        c.ge(1, "selector_initial_potential")  # a cell size in pixels
        c.ge(0, "selector_recursions")
        # epipolar search (mgso_kernels.trace)
        c.within(0, 1, "max_pix_search", open_lo=True)  # a fraction of width + height
        c.gt(0, "trace_stepsize", "trace_extra_slack_on_th")  # the number of steps divides by it; scales a threshold
        c.ge(0, "min_trace_quality", "min_trace_test_radius", "trace_gn_iterations", "trace_gn_threshold",
             "trace_slack_interval", "trace_min_improvement_factor")
        # coarse tracker (mgso.tracking.coarse_tracker)
        c.each("coarse_max_iterations", 0)
        c.gt(0, "coarse_lambda", "retrack_threshold")  # the step extrapolation divides by lambda
        c.ge(0, "coarse_lambda_extrapolation_limit", "coarse_min_step")
        c.within(0, 1, "coarse_saturated_ratio")  # a share of the residuals
        c.ge(1, "coarse_max_cutoff_repeat")  # the cutoff multiplier starts at 1
        c.ge(0, "realtime_hypothesis_budget_ms")
        c.ge(1, "coarse_abort_factor")  # below 1 a hypothesis better than the best so far would be abandoned
        c.within(0, 1, "coarse_rotation_delta", open_lo=True)  # a quaternion component
        for name in ("affine_opt_a", "affine_opt_b"):
            c.rule(getattr(self, name) == -1 or getattr(self, name) >= 0, name, "-1 (fixed) or >= 0 (estimated)")
        # keyframes (mgso.tracking.keyframe_policy): weights of the flow and brightness scores
        c.ge(0, "kf_global_weight", "kf_max_shift_t", "kf_max_shift_r", "kf_max_shift_rt", "kf_max_affine_weight",
             "kf_max_interval")
        # a factor on the first RMSE against the reference: below 1 that first frame itself would exceed it
        c.ge(1, "kf_rmse_factor", "lost_rmse_factor")
        # point activation and the fixed back end
        c.gt(0, "activation_max_pixel_interval")
        c.ge(0, "min_idepth_h_act", "activation_gn_iterations", "refine_iterations", "refine_pose_iterations",
             "refine_affine_iterations")
        # initialiser (mgso.tracking.initializer)
        c.each("init_densities", 0, strict=True)
        c.each("init_max_iterations", 0)
        c.gt(0, "init_alpha_k", "init_done_translation", "init_max_rmse")
        c.ge(0, "init_alpha_w", "init_coupling_weight", "init_frames_after_snap")
        c.within(0, 1, "init_reg_weight")  # (1 - w) own + w neighbours' median
        c.ge(2, "init_max_frames")
        c.ge(1, "init_min_points")
        # tracking loss (mgso.odometry): a share, counts, and factors on a typical motion / depth
        c.ge(0, "lost_min_rmse", "lost_min_inliers")
        c.within(0, 1, "lost_min_inlier_ratio")
        c.ge(1, "lost_max_speed_factor", "lost_speed_window")  # below 1 a frame at the median speed would be lost
        c.gt(0, "lost_max_translation")
        c.done()


@dataclass(frozen=True)
class WindowConfig:
    """DSO sliding-window bundle adjustment."""

    max_frames: int = opt(7, "keyframes in the sliding window (DSO setting_maxFrames = 7); the window has one "
                             "more slot, for the new keyframe before marginalisation")
    point_capacity: int = opt(8000, "active points the window can hold (buffers preallocated; DSO aims at 2000 "
                                    "and activation never exceeds the free capacity)")
    immature_capacity: int = opt(16000, "immature points the window can hold (about 1500 a keyframe; buffers "
                                        "preallocated; a keyframe's selection is cut to the free capacity)")
    backend: Literal["bundle", "fixed"] = opt("bundle", "bundle: DSO's joint photometric bundle adjustment with a "
                                                       "marginalisation prior (docs/window.md); fixed: the stand-in "
                                                       "(poses fixed, inverse depths refined; docs/tracking.md)")
    iterations: int = opt(6, "Gauss-Newton iterations per keyframe (DSO setting_maxOptIterations = 6)")
    min_frames: int = opt(5, "keyframes kept at least when marginalising (DSO setting_minFrames = 5)")
    affine_prior_a: float = opt(0.0, "prior on each keyframe's affine a (DSO setting_affineOptModeA; 0 = free as "
                                     "DSO's mode 1 without photometric calibration, DSO default 1e12)")
    affine_prior_b: float = opt(0.0, "prior on each keyframe's affine b (DSO setting_affineOptModeB; DSO default 1e8)")
    idepth_fix_prior: float = opt(2500.0, "prior weight on the initialiser's inverse depths: holds the scale "
                                          "(DSO setting_idepthFixPrior = 50^2)")
    idepth_fix_prior_anchored: bool = opt(False, "false: DSO's prior, centred on the point's current inverse depth "
                                                 "(it stiffens the point, no pull); true: centred on the "
                                                 "initialiser's value (mgso before 2026-11-22)")
    idepth_fix_prior_marg_fac: float = opt(360000.0, "that prior times this when such a point is marginalised "
                                                     "(DSO setting_idepthFixPriorMargFac = 600^2)")
    marg_weight_fac: float = opt(0.25, "factor on what is marginalised into the prior, for its inexact "
                                       "linearisation point (DSO setting_margWeightFac = 0.5^2)")
    orthogonalize_from: int = opt(2, "project the gauge directions out of the window's steps from this iteration on "
                                     "(0-based); 2 = DSO's default SOLVER_ORTHOGONALIZE_X_LATER, 0 = every step "
                                     "(DSO's SOLVER_ORTHOGONALIZE_X); docs/window.md compares them")
    force_accept: bool = opt(True, "keep every step even if the energy rises (DSO's default setting_forceAceptStep); "
                                   "false: a step is kept only when the total energy goes down, else undone and "
                                   "retried with more damping")

    # DSO's solver constants (FullSystemOptimize.cpp, EnergyFunctional::solveSystemF, settings.cpp)
    orthogonalize: bool = opt(True, "project the gauge directions out of the steps at all (from orthogonalize_from "
                                    "on); false: never (DSO's SOLVER_ORTHOGONALIZE_* off)")
    min_iterations: int = opt(1, "iterations before the early stop may end the optimisation "
                                 "(DSO setting_minOptIterations)")
    th_opt_iterations: float = opt(1.2, "scales the step sizes below which the optimisation stops early: larger = "
                                        "stops earlier, 0 = never (DSO setting_thOptIterations)")
    lambda_init: float = opt(1e-5, "Levenberg-Marquardt damping of the first step: DSO's default solver mode "
                                   "(SOLVER_FIX_LAMBDA) replaces FullSystem::optimize's 0.1 by 1e-5 in solveSystemF, "
                                   "Gauss-Newton with a tiny damping")
    lambda_min: float = opt(1e-5, "an accepted step lowers the damping, not below this")
    lambda_accept: float = opt(0.25, "damping factor after an accepted step (DSO FullSystem::optimize)")
    lambda_reject: float = opt(100.0, "damping factor after a step that was not finite or (force_accept false) raised "
                                      "the energy (DSO FullSystem::optimize)")
    initial_trans_prior: float = opt(1e10, "prior on a segment's first keyframe's translation, folded into the "
                                           "marginalisation prior when it leaves (DSO setting_initialTransPrior; held "
                                           "exactly while it is in the window)")
    initial_rot_prior: float = opt(1e11, "the same on its rotation (DSO setting_initialRotPrior)")
    initial_aff_a_prior: float = opt(1e14, "the same on its affine a (DSO setting_initialAffAPrior)")
    initial_aff_b_prior: float = opt(1e14, "the same on its affine b (DSO setting_initialAffBPrior)")
    frame_energy_th_n: float = opt(0.7, "a new keyframe's energy threshold starts from this quantile of its residuals' "
                                        "energies (DSO setNewFrameEnergyTH, setting_frameEnergyTHN); both back ends")
    frame_energy_th_fac_median: float = opt(1.5, "that quantile's square root times this "
                                                 "(DSO setting_frameEnergyTHFacMedian)")
    frame_energy_th_const_weight: float = opt(0.5, "... blended with the constant 26 at this weight "
                                                   "(DSO setting_frameEnergyTHConstWeight)")
    pairs_per_block: int = opt(32, "residual pairs per block of the window's linearisation kernel (each block writes "
                                   "its own partial sums)")
    # which keyframes and points leave (DSO flagFramesForMarginalization, flagPointsForRemoval); both back ends
    min_points_remaining: float = opt(0.05, "a keyframe keeping less than this share of its points leaves "
                                            "(DSO setting_minPointsRemaining)")
    max_log_aff_fac_in_window: float = opt(0.7, "a keyframe whose brightness factor to the newest exceeds exp(this) "
                                                "leaves (DSO setting_maxLogAffFacInWindow)")
    min_frame_age: int = opt(1, "the newest this many keyframes are never chosen by the distance score "
                                "(DSO setting_minFrameAge)")
    min_good_active_res_for_marg: int = opt(3, "a leaving point goes to the prior and the point cloud (else it is "
                                               "dropped) with at least this many residuals in the window "
                                               "(DSO setting_minGoodActiveResForMarg)")
    min_good_res_for_marg: int = opt(4, "... at least this many good residuals over its life "
                                        "(DSO setting_minGoodResForMarg)")
    min_idepth_h_marg: float = opt(50.0, "... and more inverse-depth Hessian than this (DSO setting_minIdepthH_marg)")

    def __post_init__(self):
        c = _Checks("window", self)
        c.within(2, 16, "max_frames")
        c.ge(100, "point_capacity", "immature_capacity")
        c.one_of(("bundle", "fixed"), "backend")
        c.within(1, 100, "iterations")
        c.within(2, self.max_frames, "min_frames")
        # prior weights (0 = none); marg_weight_fac scales down what the prior keeps
        c.ge(0, "affine_prior_a", "affine_prior_b", "idepth_fix_prior", "idepth_fix_prior_marg_fac",
             "initial_trans_prior", "initial_rot_prior", "initial_aff_a_prior", "initial_aff_b_prior")
        c.within(0, 1, "marg_weight_fac")
        c.ge(0, "orthogonalize_from", "min_iterations", "th_opt_iterations", "lambda_min", "min_idepth_h_marg")
        c.gt(0, "lambda_init", "frame_energy_th_fac_median", "max_log_aff_fac_in_window")
        c.within(0, 1, "lambda_accept", open_lo=True)  # an accepted step lowers the damping ...
        c.ge(1, "lambda_reject")  # ... a rejected one raises it
        c.within(0, 1, "frame_energy_th_n", "frame_energy_th_const_weight", "min_points_remaining")
        c.ge(1, "pairs_per_block", "min_frame_age", "min_good_active_res_for_marg", "min_good_res_for_marg")
        c.done()


@dataclass(frozen=True)
class OptimConfig:
    """Adam on the Gaussian parameters (docs/mapping.md; rates from graphdeco 3DGS ``arguments/__init__.py`` but the
    colour's and the sizes', raised for MGSO's schedule of a few thousand steps)."""

    lr_means_init: float = opt(1.6e-4, "means learning rate at step 0, times scene extent (3DGS position_lr_init)")
    lr_means_final: float = opt(1.6e-6, "means learning rate at lr_means_max_steps, times extent (3DGS final)")
    lr_means_max_steps: int = opt(30_000, "steps of the log-linear means decay, constant after (3DGS max_steps)")
    lr_means_delay_steps: int = opt(0, "warm-up steps scaled by lr_means_delay_mult (3DGS default 0 = none)")
    lr_means_delay_mult: float = opt(0.01, "means lr factor at step 0 of the warm-up (3DGS position_lr_delay_mult)")
    lr_log_scales: float = opt(0.01, "log-scale learning rate (twice 3DGS's scaling_lr 0.005: MGSO's map trains a "
                                     "few thousand steps, not 30,000; docs/mapping.md, \"Rates for a short schedule\")")
    lr_quats: float = opt(0.001, "raw quaternion learning rate (3DGS rotation_lr)")
    lr_opacity: float = opt(0.025, "opacity-logit learning rate (3DGS opacity_lr; 0.05 before the 2024 update)")
    lr_sh_dc: float = opt(0.01, "SH DC (base colour) learning rate (four times 3DGS's feature_lr 0.0025, for a short "
                                "schedule as lr_log_scales)")
    lr_sh_rest: float = opt(0.0025 / 20.0, "higher SH bands learning rate (3DGS's feature_lr / 20; unused at "
                                           "MGSO's mapping.sh_degree 0)")
    beta1: float = opt(0.9, "Adam first-moment decay (3DGS/torch default)")
    beta2: float = opt(0.999, "Adam second-moment decay (3DGS/torch default)")
    eps: float = opt(1e-15, "Adam epsilon (3DGS uses 1e-15 so tiny colour/opacity gradients still move)")
    bias_correction: Literal["per_gaussian", "global", "none"] = opt(
        "per_gaussian", "per_gaussian: a Gaussian added late starts Adam at t=1 (MGSO adds seeds every keyframe); "
                        "global: one step count (3DGS); none: no correction (gsplat fused adam)")
    sparse: bool = opt(False, "update only Gaussians visible in this view (3DGS sparse_adam, gsplat visible_adam); "
                              "false = dense torch.optim.Adam as 3DGS by default")
    lr_exposure_init: float = opt(0.01, "per-keyframe exposure (a, b) learning rate at step 0 (3DGS exposure_lr_init)")
    lr_exposure_final: float = opt(0.001, "exposure learning rate at lr_means_max_steps (3DGS exposure_lr_final)")

    def __post_init__(self):
        c = _Checks("mapping.optim", self)
        c.ge(0, "lr_means_init", "lr_means_final", "lr_means_max_steps", "lr_means_delay_steps", "lr_log_scales",
             "lr_quats", "lr_opacity", "lr_sh_dc", "lr_sh_rest", "lr_exposure_init", "lr_exposure_final")
        c.within(0, 1, "lr_means_delay_mult")  # the warm-up's factor rises from it to 1
        c.within(0, 1, "beta1", "beta2", open_hi=True)  # Adam's moment decays
        c.gt(0, "eps")  # Adam divides by sqrt(v) + eps, and v is 0 for a parameter without gradient
        c.one_of(("per_gaussian", "global", "none"), "bias_correction")
        c.done()


@dataclass(frozen=True)
class DensifyConfig:
    """Densification and pruning (3DGS adaptive density control; gsplat ``DefaultStrategy`` names in brackets)."""

    refine_start_step: int = opt(500, "no clone/split/prune before this step: stats need a few views (3DGS 500)")
    refine_stop_step: int = opt(15_000, "no clone/split/prune/reset from this step on (3DGS 15000); 0 = never stop "
                                        "(continuous SLAM mapping)")
    refine_every: int = opt(100, "steps between refinements (3DGS densification_interval)")
    reset_every: int = opt(3000, "steps between opacity resets; 0 = never (3DGS opacity_reset_interval)")
    reset_opacity_value: float = opt(0.01, "opacity clamp at a reset, so floaters must earn opacity back (3DGS 0.01)")
    pause_refine_after_reset: int = opt(0, "skip refinements this many steps after a reset (gsplat; 0 = off)")
    grad_mode: Literal["grad", "absgrad", "absgs"] = opt(
        "grad", "grad: 3DGS mean gradient; absgrad: gsplat's AbsGS variant (abs grad for clone and split); "
                "absgs: AbsGS paper (clone by grad, split by abs grad)")
    grow_grad2d: float = opt(0.0002, "clone/split above this mean |dL/d mean2d| in NDC units (3DGS "
                                     "densify_grad_threshold); NDC = pixels x W/2, H/2")
    grow_grad2d_abs: float = opt(0.0008, "abs-gradient threshold, NDC units, in grad_mode absgrad (gsplat docs "
                                         "recommend 0.0008)")
    absgs_split_grad2d: float = opt(0.0004, "abs-gradient split threshold in grad_mode absgs (AbsGS "
                                            "densify_grad_abs_threshold)")
    percent_dense: float = opt(0.01, "clone if max scale <= this x scene extent, else split (3DGS percent_dense, "
                                     "gsplat grow_scale3d)")
    split_children: int = opt(2, "Gaussians a split makes from one (3DGS N = 2)")
    split_scale_factor: float = opt(0.8, "children scales = parent / (factor x children) (3DGS 0.8 -> / 1.6)")
    grow_min_views: int = opt(1, "a Gaussian must be visible in this many views since the last refine to grow")
    prune_opacity: float = opt(0.005, "prune below this opacity (3DGS min_opacity, gsplat prune_opa)")
    prune_scale3d: float = opt(0.1, "after the first opacity reset, prune max scale above this x scene extent (3DGS, "
                                    "gsplat); without resets (reset_every 0, MGSO's mapper) never")
    prune_screen_px: float = opt(0.0, "after the first opacity reset, prune screen radius above this many pixels; 0 = "
                                      "off (3DGS's 20 px never fires, graphdeco issue #123; gsplat defaults it off)")
    max_aspect: float = opt(0.0, "at each refine, shorten axes longer than this x the Gaussian's shortest axis "
                                 "(needles that disagreeing views stretch become discs); 0 = off (3DGS)")
    prune_min_age: int = opt(0, "steps a new Gaussian is safe from pruning (0 = 3DGS); raise for SLAM seeding")
    prune_weight_px: float = opt(0.0, "at each refine, prune Gaussians in view in at least prune_weight_views "
                                      "training views since the last refine whose blending weight (alpha T) summed "
                                      "over each view's pixels stayed below this many full-resolution pixels in all "
                                      "of them: hidden behind opaque Gaussians or too faint to show, each still costs "
                                      "every step its projection, tiles and sort (the blending-weight importance of "
                                      "3DGS pruning work, taken per view); 0 = off (3DGS)")
    prune_weight_views: int = opt(3, "views a Gaussian must have been in since the last refine before "
                                     "prune_weight_px judges it")
    sort_spatially: bool = opt(True, "after each refine, put the map's rows in the Z-order of their means, so that a "
                                     "view culls whole runs of rows (the CPU's per-Gaussian kernels pass over them; "
                                     "docs/mapping.md); false = rows stay in the order they were made")

    def __post_init__(self):
        c = _Checks("mapping.densify", self)
        c.ge(0, "refine_start_step", "refine_stop_step", "reset_every", "pause_refine_after_reset", "grow_min_views",
             "prune_min_age", "percent_dense", "prune_screen_px", "prune_weight_px")
        c.ge(1, "prune_weight_views")
        c.ge(1, "refine_every")  # step % refine_every
        c.within(0, 1, "reset_opacity_value", open_lo=True, open_hi=True)  # an opacity (its logit is stored)
        c.within(0, 1, "prune_opacity", open_hi=True)
        c.one_of(("grad", "absgrad", "absgs"), "grad_mode")
        c.gt(0, "grow_grad2d", "grow_grad2d_abs", "absgs_split_grad2d", "prune_scale3d")
        c.ge(2, "split_children")  # a split into one is no split
        c.gt(0, "split_scale_factor")  # the children's scales divide by it
        c.rule(self.max_aspect == 0 or self.max_aspect >= 1, "max_aspect", "0 (off) or >= 1")
        c.done()


@dataclass(frozen=True)
class TrainConfig:
    """Training the map on posed views: the step MGSO's mapper runs, and ``mgso fit`` (docs/fitting.md)."""

    iterations: int = opt(3000, "training steps of `mgso fit` (3DGS runs 30 000 on a GPU; a few thousand is a CPU-sized "
                                "run)")
    background: tuple[float, float, float] = opt((0.0, 0.0, 0.0), "RGB behind the Gaussians in renders (3DGS: black)")
    min_scene_extent: float = opt(1.0, "floor of the scene extent (world units) from the camera centres: few or "
                                       "close cameras would make the means rate and size thresholds tiny")
    learn_exposure: bool = opt(False, "learn an affine brightness (a, b) per view with its own Adam, the loss compares "
                                      "exp(a) render + b with the image (MGSO; off for fit: held-out frames have none)")
    pyramid_levels: int = opt(1, "Gaussian-pyramid training (Photo-SLAM): levels of 2x2-averaged images; 1 = full "
                                 "resolution only")
    pyramid_uses: int = opt(2, "times a view is trained at each coarser level before the next finer one "
                               "(Photo-SLAM's per-keyframe times of use)")
    sh_degree_interval: int = opt(1000, "raise the SH degree in use by one every this many steps up to "
                                        "mapping.sh_degree (3DGS oneupSHdegree); 0 = full degree from the start")
    depth_weight: float = opt(0.2, "weight of the sparse depth term: mean relative error between the render's "
                                   "expected depth and the view's depth points (MGSO: DSO's points of the keyframe, "
                                   "only where they agree with the map (mapping.seeding.depth_rule_max_median): "
                                   "a handheld camera's poor depths pulled the map to them; `mgso fit`'s views have "
                                   "none); 0 = off")
    refine_poses: bool | None = opt(None, "also optimise views' world_to_cam with the rasteriser's pose gradient "
                                          "(left perturbation; the first keyframe holds the gauge); null = in MGSO's "
                                          "mapper the keyframes whose depths disagree with the map (the seeding's "
                                          "depth rule stood down: a handheld camera's segments disagree by degrees), "
                                          "in `mgso fit` none (given poses, trusted); true = every view; false = none")
    lr_pose_translation: float = opt(0.003, "Adam rate of the pose translation delta, world units (MonoGS's "
                                            "cam_trans_delta is 0.001, the default until 2026-12-06: the mapper's "
                                            "untrusted keyframes converged too slowly; freiburg1_rpy's replays "
                                            "gained 0.33-1.06 dB at three times both rates, lost 0.04 at six times; "
                                            "docs/mapping.md)")
    lr_pose_rotation: float = opt(0.009, "Adam rate of the pose rotation delta, radians (MonoGS's cam_rot_delta is "
                                         "0.003, the default until 2026-12-06; see lr_pose_translation)")
    metrics_every: int = opt(10, "compute the training PSNR every n steps (reads the render back to the host); 0 = "
                                 "never")
    init_points: int = opt(20_000, "random initial points in the view frusta for `mgso fit --init random` (3DGS's "
                                   "random init uses 100 000 in a box)")
    init_depth_range: tuple[float, float] = opt((0.5, 5.0), "camera depth range of random initial points, world "
                                                            "units (metres for an indoor RGB-D dataset)")
    init_max_screen_px: float = opt(3.0, "random initial points: scale at most this many pixels (one sigma) in the "
                                         "view a point was drawn from; sparse random points' kNN scales cover the "
                                         "image and make CPU steps slow; 0 = no cap (3DGS)")
    init_opacity: float = opt(0.1, "opacity of new Gaussians (3DGS, MGSO)")
    init_knn: int = opt(3, "initial scale = mean distance to this many nearest neighbours (3DGS, MGSO)")
    holdout_every: int = opt(5, "`mgso fit` holds out every n-th frame for evaluation (never trained on); 0 = none")
    max_train_views: int = opt(0, "`mgso fit` trains on at most this many views, evenly spread; 0 = all")

    def with_pose_refinement(self, default: bool) -> "TrainConfig":
        """This section with ``refine_poses`` decided: ``default`` where it is null (the mapper passes True for
        the odometry's poses, `mgso fit` False for given ones), else as set."""
        return dataclasses.replace(self, refine_poses=default if self.refine_poses is None else self.refine_poses)

    def __post_init__(self):
        c = _Checks("mapping.train", self)
        c.ge(0, "iterations", "pyramid_uses", "sh_degree_interval", "depth_weight", "lr_pose_translation",
             "lr_pose_rotation", "metrics_every", "init_max_screen_px", "holdout_every", "max_train_views")
        c.ge(1, "pyramid_levels", "init_points", "init_knn")
        c.rule(len(self.background) == 3 and all(0 <= v <= 1 for v in self.background), "background",
               "three values (RGB) in [0, 1]")
        c.gt(0, "min_scene_extent")  # rates and size thresholds are multiples of the extent
        c.rule(0 < self.init_depth_range[0] < self.init_depth_range[1], "init_depth_range",
               "(near, far) with 0 < near < far")
        c.within(0, 1, "init_opacity", open_lo=True, open_hi=True)  # stored as its logit
        c.done()


@dataclass(frozen=True)
class SeedingConfig:
    """MGSO's seeding of new Gaussians from DSO's points at each keyframe (docs/seeding.md)."""

    enabled: bool = opt(True, "seed Gaussians from each keyframe's DSO points (MGSO); false: the map grows by "
                              "densification only")
    use_immature: bool = opt(True, "also seed immature points with a good depth interval (MGSO: tracked pixels not "
                                   "used for the pose)")
    min_point_weight: float = opt(0.0, "drop points whose weight (e.g. DSO's inverse-depth Hessian) is below this; "
                                       "0 keeps all")
    fill: bool = opt(True, "add points inside large Delaunay triangles of the points (MGSO's low-gradient fill)")
    fill_min_triangle_area_px: float = opt(100.0, "fill triangles larger than this (px^2 at keyframe resolution; "
                                                  "DSO's 2000 points at 640x480 give 77 px^2 per triangle)")
    fill_depth: Literal["mean", "barycentric"] = opt(
        "barycentric", "fill depth: mean of the vertex depths (MGSO) or barycentric inverse depth (exact on planes; "
                       "measured better, docs/seeding.md)")
    fill_max_depth_ratio: float = opt(1.5, "skip triangles whose farthest / nearest vertex depth exceeds this: they "
                                           "straddle a depth edge and their fill would float between surfaces "
                                           "(1.5: as few floaters as 1.3, half the rejections; docs/seeding.md)")
    fill_area_per_point_px: float = opt(400.0, "a triangle gets k^2 spread points, k = ceil(sqrt(area / this)); "
                                               "below this area its centroid only")
    fill_max_subdivisions: int = opt(4, "cap of k above (at most k^2 = 16 points per triangle)")
    max_depth_factor: float = opt(100.0, "drop a point deeper than this times the median depth of its message's "
                                         "points: DSO's active points that the window drove to nearly zero inverse "
                                         "depth lie 1e3-1e10 times farther (0.2 % of 7-Scenes' points, 0.06 % of "
                                         "KITTI's; docs/seeding.md); 0 = no limit")
    visibility_threshold: float = opt(0.5, "keep a candidate only where the map's alpha is below this (the pixel is "
                                           "mostly empty; SplaTAM's silhouette threshold 0.5)")
    depth_tolerance: float = opt(0.1, "also keep a candidate the map covers when the map's expected depth there is "
                                      "off the point's by more than this fraction (the map has no surface where "
                                      "the odometry measured one: SplaTAM's depth-error rule; docs/seeding.md); 0 = "
                                      "alpha only")
    depth_rule_max_median: float = opt(0.5, "skip the depth rule for a keyframe whose covered candidates' median "
                                            "relative depth error (the odometry's depth against the map's) is above "
                                            "this: when most of them disagree, the disagreement is the odometry's "
                                            "noise, not surfaces the map lacks (a handheld camera's: medians 0.46-3.8 "
                                            "on TUM freiburg1_rpy, where every keyframe seeded its points again and "
                                            "the map grew with the run into transparent fog; the synthetic demo's "
                                            "0.03-0.10, 7-Scenes' 0.02-0.2 with a stretch up to 0.6; 0.25 left 16 of "
                                            "7-Scenes' 79 keyframes untrusted (21.24 dB), 0.4 six (21.46 dB), 0.5 "
                                            "none (21.63 dB); "
                                            "docs/mapping.md, \"Handheld camera\"); such a keyframe is not trusted: "
                                            "no depth term, its pose refined (mapping.train.refine_poses null); 0 = "
                                            "never skip")
    distrust_median: float = opt(2.0, "once three keyframes' median relative depth error against the map "
                                       "(Mapper.DISTRUST_KEYFRAMES) is above this (the map's depths three times the "
                                       "odometry's or more: its scale broke, as a handheld camera's does), the run's "
                                       "odometry is not trusted: every keyframe, earlier ones included, has its pose "
                                       "refined and no depth term (TUM freiburg1_rpy: medians up to 4,000, the "
                                       "deterministic map +0.4 and +2.5 dB with two odometry seeds; 7-Scenes, KITTI "
                                       "and the out-and-back never above 0.92; docs/mapping.md, \"A broken scale\"); "
                                       "0 = judge each keyframe alone")
    alpha_downscale: int | None = opt(None, "render the coverage alpha at 1/this resolution (a quarter of the "
                                            "blending work at 2); null = 4 in real time (7-Scenes at 640x480 on 2 "
                                            "cores: the seeding 24-30 % cheaper, 41-44 % more training steps while "
                                            "the camera ran, the PSNR within the runs' spread), 2 in the "
                                            "deterministic mode (at 4 the replays lose 0.02-0.11 dB; "
                                            "docs/seeding.md)")
    coverage_stop: float = opt(0.01, "the coverage render stops a pixel once its transmittance is below this: the "
                                     "alpha test stays exact below 1 - this, the expected depth misses at most this "
                                     "weight, and the blending on a dense map costs about 40 % less "
                                     "(docs/seeding.md); 0 = the full render's 1e-4")
    min_new_gaussians: int = opt(30, "add nothing when fewer candidates survive the visibility filter (MGSO: 30)")
    init_opacity: float = opt(0.1, "opacity of new Gaussians (MGSO, 3DGS)")
    knn: int = opt(3, "scale = mean distance to this many nearest neighbours among new and visible Gaussians "
                      "(MGSO, 3DGS)")
    scale_min_px: float = opt(0.5, "smallest initial scale, in pixels of the keyframe (x depth / f in world units)")
    scale_max_px: float = opt(8.0, "largest initial scale, in keyframe pixels: a lonely point does not become a "
                                   "fog over the view, and the large seeds of the low-gradient fill do not make "
                                   "every pixel blend more Gaussians (20 before 2026-12-07: the replays as good, "
                                   "their training 1-19 % shorter; docs/seeding.md)")

    def __post_init__(self):
        c = _Checks("mapping.seeding", self)
        c.ge(0, "min_point_weight", "fill_min_triangle_area_px", "depth_tolerance", "min_new_gaussians",
             "depth_rule_max_median", "distrust_median")
        c.gt(0, "fill_area_per_point_px")  # k = ceil(sqrt(area / this))
        c.one_of(("mean", "barycentric"), "fill_depth")
        c.ge(1, "fill_max_depth_ratio", "fill_max_subdivisions", "knn")
        if self.alpha_downscale is not None:
            c.ge(1, "alpha_downscale")
        c.rule(self.max_depth_factor == 0 or self.max_depth_factor >= 1, "max_depth_factor", "0 (no limit) or >= 1")
        c.within(0, 1, "visibility_threshold", open_lo=True)  # an alpha
        # a pixel stopped by the coverage stop has alpha > 1 - coverage_stop: it must still read as covered (with
        # visibility_threshold 1 nothing is ever covered, whatever the stop)
        c.rule(0 <= self.coverage_stop < 1 and (self.coverage_stop <= 1 - self.visibility_threshold
                                                or self.visibility_threshold >= 1), "coverage_stop",
               f">= 0 and <= 1 - visibility_threshold ({1 - self.visibility_threshold:g})")
        c.within(0, 1, "init_opacity", open_lo=True, open_hi=True)  # stored as its logit
        c.gt(0, "scale_min_px")
        c.rule(self.scale_max_px >= self.scale_min_px, "scale_max_px", f">= scale_min_px ({self.scale_min_px})")
        c.done()


@dataclass(frozen=True)
class MapperConfig:
    """MGSO's mapping thread: how keyframe messages become training views and how much it trains (docs/mgso.md)."""

    iterations_per_keyframe: int = opt(20, "deterministic mode: training steps after each keyframe message (real "
                                           "time trains as much as it can instead); a CPU-sized budget, the rest "
                                           "of it spent at the end (final_iterations; docs/mapping.md)")
    final_iterations: int | None = opt(None, "final refinement after the last frame: steps over all keyframes, "
                                             "chosen as while running; the keyframes that came last were trained "
                                             "least, and these steps even it out (7-Scenes 640x480, uniform "
                                             "sampling: 22.26 dB with 20 a keyframe + 1,300, 22.36 dB with 40 + 300 "
                                             "but its last frames at 13.9 dB); null = 2,000 in the deterministic "
                                             "mode (1,300 until 2026-12-06: 2,000 with final_coarse_share 0.8 gave "
                                             "7-Scenes 23.11 against 22.42 dB in less time; docs/mapping.md), "
                                             "1,600 in real time (the map's wait after the stream; 1,300 until "
                                             "2026-12-06, when the first 40 % went one level coarser: "
                                             "final_coarser_share); 0 = none")
    final_budget_s: float | None = opt(None, "real time: the time the final refinement may fill, in seconds: past its "
                                             "planned share its coarse steps (at the level of running_max_pixels) go "
                                             "on while the time left holds one more and the full-resolution steps at "
                                             "its end (timed on two of them), up to twice their planned count; never "
                                             "fewer steps than planned; null = 55 in real time with the map on the "
                                             "CPU (issue 42 asks the map within 60 s; docs/mapping.md, \"The "
                                             "real-time final refinement in a time budget\"), 0 (final_iterations "
                                             "alone) on CUDA and in the deterministic mode")
    running_max_pixels: int = opt(80_000, "real time: while the stream runs, train each view at the finest level of "
                                          "its pyramid with at most this many pixels (a 640x480 view at 320x240: a "
                                          "step 2.9x cheaper on the 2-core CPU, docs/mgso.md); the final "
                                          "refinement's first steps too (final_coarse_share); 0 = full resolution")
    final_coarse_share: float | None = opt(None, "the share of the final refinement's steps (its first) trained at "
                                                "the level running_max_pixels gives, the rest at full resolution; "
                                                "null = 0.95 in real time (7-Scenes on 2 cores: the final 1,300 "
                                                "steps in 122 s, 129-151 s at 0.8, 235-306 s at 0, the PSNR within "
                                                "the runs' spread); in the deterministic mode with its 2,000 final "
                                                "steps and its coarse steps after each keyframe 0.8 where that level "
                                                "has at least 50,000 pixels (320x240 of a 640x480 camera), 0.6 "
                                                "below, where KITTI's 310x94 lost 0.19-0.24 dB at 0.8 (0.6 "
                                                "everywhere until 2026-12-07: docs/mapping.md, \"The deterministic "
                                                "final refinement a level coarser\"); 0.8 with the steps after "
                                                "each keyframe at full resolution")
    final_coarser_share: float | None = opt(None, "the share of the final refinement's steps (its first, within "
                                                 "final_coarse_share) trained one pyramid level coarser still "
                                                 "(160x120 for a 640x480 camera); null = 0.6 in real time (0.4 "
                                                 "until 2026-12-07, when the replays of its schedule gained 0.07-0.17 "
                                                 "dB with 0.6 and three real-time rounds of 7-Scenes 0.15-1.5 dB in a "
                                                 "final refinement 6-11 s shorter; 0.4 against 1,300 steps: +0.43, "
                                                 "+0.28, +0.28 dB on 7-Scenes, freiburg1_rpy and KITTI; "
                                                 "docs/mapping.md), 0.4 in the deterministic mode (0 until "
                                                 "2026-12-07: its replays with 0.4 as fast or faster at the same "
                                                 "PSNR on 7-Scenes and KITTI)")
    keyframe_steps_coarse: bool = opt(True, "deterministic mode: the steps after each keyframe train at the level "
                                            "running_max_pixels gives, as the real-time mapper's steps while the "
                                            "stream runs (the final refinement: final_coarse_share); with the "
                                            "final refinement's last 40 % at full resolution the mapping took 27-48 "
                                            "% less time than at full resolution, at -0.01, +0.07 and +0.11 dB on "
                                            "7-Scenes, freiburg1_rpy and KITTI (docs/mapping.md); false: full "
                                            "resolution (the default until 2026-12-06)")
    running_train_share: float = opt(0.25, "real time: the share of the mapper's busy time kept for training while "
                                           "messages wait (a mapper that trains only when its queue is empty never "
                                           "trains on a small CPU: seeding the keyframes fills what the odometry "
                                           "leaves; docs/mgso.md), unless half the queue is full; 0 = train only "
                                           "when the queue is empty")
    running_training: bool = opt(True, "real time: train while the stream runs (MGSO's decoupled mapper); false: "
                                       "only apply the messages until the stream ends, and make the map in the "
                                       "final refinement")
    defer_seeding_above: int = opt(128, "real time: with at least this many messages queued, a keyframe's seeding "
                                        "waits like the marginalised points (seeded with its host's points once "
                                        "the queue is empty, a second at a time), so that a mapper behind the "
                                        "camera catches up on its messages and the queue does not fill (on 2 cores "
                                        "it filled in 80 s of a 640x480 camera and the odometry waited; "
                                        "docs/mgso.md); 0 = never")
    seed_points_settled: bool = opt(True, "real time: a host keyframe's marginalised points wait until it has left the "
                                          "odometry's window (its pose updates no longer name it), so that one "
                                          "coverage render seeds them all, instead of one render for each keyframe "
                                          "that marginalised some (docs/seeding.md); false: seeded whenever the "
                                          "queue is empty")
    queue_size: int = opt(1024, "bounded message queue (odometry -> mapper): a few hundred keyframes of a typical run "
                                "with their pose updates fit, so the odometry waits only when the mapper is hopelessly "
                                "behind (each wait is counted and reported)")
    newest_probability: float = opt(0.0, "chance that a step trains on the newest keyframe; otherwise the sampler's "
                                         "choice among all keyframes (0.2 with 40 steps a keyframe + 300 final, the "
                                         "defaults before 2026-12-02, spent a fifth of the steps on the keyframe "
                                         "just added: 7-Scenes 640x480 21.51 against 22.26 dB, the oracle 20.66 "
                                         "against 21.54 dB; docs/mapping.md)")
    sampler: Literal["random", "least_used"] = opt(
        "random", "which keyframe a step trains on besides the newest: random = uniform over all keyframes "
                  "(NewestOrRandomSampler); least_used = one of the least used (LeastUsedSampler: with a fixed "
                  "number of steps a keyframe the newest takes them all, and the map forgot its first keyframes: "
                  "7-Scenes 640x480 18.25 dB with least_used, 21.87 dB with random; docs/mapping.md)")
    loss_share: float | None = opt(None, "sampler random: the share of each choice of keyframe made in proportion "
                                         "to the keyframes' latest losses at the step's pyramid level (the rest "
                                         "uniform), so that the keyframes the map fits worst (a place few keyframes "
                                         "see, the stream's first and last) are trained more often; null = 0.5 in "
                                         "the deterministic mode (its replays +0.08, +0.66 and +0.13 dB on "
                                         "7-Scenes, freiburg1_rpy and KITTI), 0 (uniform, the default before "
                                         "2026-12-07) in real time, where three pairs of freiburg1_rpy runs came "
                                         "out below (docs/mapping.md, \"Keyframes drawn by their loss\")")
    init: Literal["dso", "random"] = opt(
        "dso", "dso: seed Gaussians from DSO's points (MGSO); random: as many random points in the keyframe's "
               "frustum as DSO seeding would add there, depth uniform over its points' depth range (the comparison "
               "MGSO's claim is measured against)")
    seed_marginalized: bool = opt(True, "also seed from marginalised points (final depths) where the map is still "
                                        "empty, seen from their host keyframe (MGSO)")
    min_train_views: int = opt(1, "no training before this many keyframes reached the map")
    opacity_reset: bool = opt(False, "keep mapping.densify's periodic opacity reset (3DGS); off: a reset makes the "
                                     "whole map nearly transparent, so the next keyframes' visibility test would "
                                     "seed everywhere again (SplaTAM and MGSO's seeding rule add by coverage)")

    exposure: Literal["odometry", "exposure_time", "none"] = opt(
        "exposure_time", "each view's brightness model in training and evaluation: odometry = DSO's affine (a, b) and "
                         "the exposure time; exposure_time = the exposure time's gain only (without photometric "
                         "calibration DSO's affine drifts in its gauge: docs/mgso.md); none = the image as it is")
    refine_every: int = opt(300, "the mapper's densification interval in steps, in place of mapping.densify."
                                 "refine_every (3DGS's 100, what `mgso fit` uses): keyframes that disagree make "
                                 "densification every 100 steps grow floaters (docs/mapping.md); 0 = mapping.densify's")
    loop_refines_poses: bool = opt(True, "once a loop correction moved the map, the map refines the poses of the "
                                         "keyframes it moved (the first keyframe holds the gauge; needs "
                                         "mapping.train.refine_poses not false): the pose graph's solution is "
                                         "closer to the truth but not consistent with the images the way the "
                                         "odometry's poses and depths were (7-Scenes out and back, 55 loops: "
                                         "18.51 dB with those poses held, 20.88 refined, 20.19 without loop "
                                         "closure; docs/loop.md)")
    loop_moves_untrusted: bool = opt(False, "loop closure's corrections move the map's keyframes and Gaussians also "
                                            "once the run's odometry is not trusted (mapping.seeding."
                                            "distrust_median); false: the map, which then refines every pose "
                                            "itself (mapping.train.refine_poses not false), holds them and only the "
                                            "odometry's poses move (TUM "
                                            "freiburg1_rpy, 27 loops: 19.70 dB moving the map, 20.30 holding it, "
                                            "20.36 without loop closure; docs/loop.md)")
    prune_opacity: float = opt(0.05, "the mapper's prune threshold at each refinement, in place of mapping."
                                     "densify.prune_opacity (3DGS's 0.005, what `mgso fit` uses): views that disagree "
                                     "leave many faint Gaussians in a SLAM map; 0.05 halves the 7-Scenes map (6.14 -> "
                                     "3.08 MB) for 0.22 dB and cuts KITTI's by a third at equal PSNR "
                                     "(docs/mapping.md); 0 = mapping.densify's")
    prune_weight_px: float | None = opt(None, "the mapper's weight prune at each refinement, in place of "
                                              "mapping.densify.prune_weight_px (off in 3DGS and `mgso fit`): "
                                              "Gaussians whose blending weight summed over a view stayed below this "
                                              "many full-resolution pixels in every view since the last refinement "
                                              "(hidden behind the surface others make, or too faint to show; a "
                                              "handheld camera's seedings leave many); null = 0.1 in real time, 0 "
                                              "in the deterministic mode, where its replays lost 0.10-0.15 dB "
                                              "(docs/mapping.md, \"Pruning what no view shows\"); 0 = "
                                              "mapping.densify's")
    final_refine_after: int = opt(200, "where the stream left the map unrefined (real time on a small CPU: a few "
                                       "steps while the camera ran, every seed untrained; 7-Scenes' 118k Gaussians "
                                       "then cost 275-331 ms a step until the schedule's first refinement at step "
                                       "600), the final refinement densifies and prunes this many steps in; a map "
                                       "refined while the stream ran keeps its schedule; 0 = the schedule alone")
    grow_grad2d: float = opt(0.0008, "the mapper's clone/split threshold (grad_mode grad), in place of mapping."
                                     "densify.grow_grad2d (3DGS's 0.0002, what `mgso fit` uses): with every keyframe "
                                     "trained to the end the map grows where its views disagree (7-Scenes 640x480: "
                                     "157k Gaussians, 10.7 MB at 0.0002; KITTI 397k, 27 MB); docs/mapping.md; "
                                     "0 = mapping.densify's")

    def final_steps(self, realtime: bool) -> int:
        """``final_iterations`` with its null resolved for the mode: 2,000 deterministic, 1,600 in real time."""
        if self.final_iterations is not None:
            return int(self.final_iterations)
        return 1600 if realtime else 2000

    def weight_prune_px(self, realtime: bool) -> float:
        """``prune_weight_px`` with its null resolved for the mode: 0.1 in real time, 0 (mapping.densify's)
        deterministic."""
        if self.prune_weight_px is not None:
            return float(self.prune_weight_px)
        return 0.1 if realtime else 0.0

    def draw_loss_share(self, realtime: bool) -> float:
        """``loss_share`` with its null resolved for the mode: 0.5 deterministic, 0 in real time."""
        if self.loss_share is not None:
            return float(self.loss_share)
        return 0.0 if realtime else 0.5

    def final_budget(self, realtime: bool, cpu: bool) -> float:
        """``final_budget_s`` with its null resolved: 55 s in real time on the CPU, 0 (none) otherwise."""
        if self.final_budget_s is not None:
            return float(self.final_budget_s)
        return 55.0 if realtime and cpu else 0.0

    # the deterministic mode's final refinement keeps 80 % of its steps at the coarse level only where that level has
    # this many pixels (7-Scenes' and freiburg1_rpy's 320x240); KITTI's 310x94 needs 40 % at full resolution
    COARSE_DETAIL_PIXELS = 50_000

    def final_share_coarse(self, realtime: bool, coarse_pixels: int | None = None) -> float:
        """``final_coarse_share`` with its null resolved for the mode: 0.95 in real time; deterministic 0.8 where the
        coarse level's image (``coarse_pixels``, width x height; None: unknown) has at least
        ``COARSE_DETAIL_PIXELS``, 0.6 below, and 0.8 where the steps after each keyframe train at full resolution
        (``keyframe_steps_coarse`` false)."""
        if self.final_coarse_share is not None:
            return float(self.final_coarse_share)
        if realtime:
            return 0.95
        if not self.keyframe_steps_coarse:
            return 0.8
        return 0.8 if coarse_pixels is not None and coarse_pixels >= self.COARSE_DETAIL_PIXELS else 0.6

    def final_share_coarser(self, realtime: bool) -> float:
        """``final_coarser_share`` with its null resolved for the mode: 0.6 in real time, 0.4 deterministic."""
        if self.final_coarser_share is not None:
            return float(self.final_coarser_share)
        return 0.6 if realtime else 0.4

    def __post_init__(self):
        c = _Checks("mapping.mapper", self)
        c.ge(0, "iterations_per_keyframe", "refine_every", "running_max_pixels", "defer_seeding_above",
             "final_refine_after")
        if self.final_iterations is not None:
            c.ge(0, "final_iterations")
        if self.final_budget_s is not None:
            c.ge(0, "final_budget_s")
        c.within(0, 1, "running_train_share", open_hi=True)    # a share of 1 would never handle a message
        if self.final_coarse_share is not None:
            c.within(0, 1, "final_coarse_share")
        if self.final_coarser_share is not None:
            c.within(0, 1, "final_coarser_share")
        c.within(0, 1, "prune_opacity", open_hi=True)
        c.ge(0, "grow_grad2d")
        if self.prune_weight_px is not None:
            c.ge(0, "prune_weight_px")
        c.ge(1, "queue_size", "min_train_views")
        c.within(0, 1, "newest_probability")
        if self.loss_share is not None:
            c.within(0, 1, "loss_share")
        c.one_of(("odometry", "exposure_time", "none"), "exposure")
        c.one_of(("dso", "random"), "init")
        c.one_of(("random", "least_used"), "sampler")
        c.done()


@dataclass(frozen=True)
class MappingConfig:
    """Gaussian splatting map and its training."""

    enabled: bool = opt(True, "the full stage always builds the map: false is refused (it did nothing); the odometry "
                              "alone is `mgso run --stage odometry`")
    capacity: int = opt(500_000, "most Gaussians the map holds (buffers preallocated; ~130 MB at SH degree 0)")
    sh_degree: int = opt(0, "spherical-harmonics degree of colour; 0 = view-independent RGB (MGSO; 3DGS uses 3)")
    lambda_dssim: float = opt(0.2, "weight of D-SSIM in the loss, L = (1-l) L1 + l (1-SSIM) (3DGS lambda_dssim)")
    scene_extent_margin: float = opt(1.1, "scene extent = this x max camera distance from their centroid (3DGS)")
    optim: OptimConfig = field(default_factory=OptimConfig, metadata={"reason": "Adam settings of the map"})
    densify: DensifyConfig = field(default_factory=DensifyConfig,
                                   metadata={"reason": "densification and pruning rules"})
    train: TrainConfig = field(default_factory=TrainConfig,
                               metadata={"reason": "training on posed views (the step, fit, initial points)"})
    seeding: SeedingConfig = field(default_factory=SeedingConfig,
                                   metadata={"reason": "MGSO's seeding of Gaussians from DSO's points"})
    mapper: MapperConfig = field(default_factory=MapperConfig,
                                 metadata={"reason": "MGSO's mapping thread: messages, training budget, queue"})

    def __post_init__(self):
        c = _Checks("mapping", self)
        c.rule(self.enabled, "enabled", "true (the odometry alone: mgso run --stage odometry)")
        c.ge(1, "capacity")
        c.within(0, 3, "sh_degree")  # the SH kernels evaluate degrees 0..3 (mgso_kernels.splat.sh)
        c.within(0, 1, "lambda_dssim")  # L = (1 - l) L1 + l D-SSIM
        c.gt(0, "scene_extent_margin")
        c.done()


@dataclass(frozen=True)
class OutputConfig:
    trajectory_format: str = opt("tum", "trajectory.txt is always TUM (timestamp tx ty tz qx qy qz qw); kitti also "
                                        "writes trajectory_kitti.txt and keyframes_kitti.txt (3x4 rows)")
    save_renders: bool = opt(True, "write renders of evaluation frames next to the input")
    plot: bool = opt(True, "write trajectory.png (with ground truth) and, for a full run, report.png")

    def __post_init__(self):
        c = _Checks("output", self)
        c.one_of(TRAJECTORY_FORMATS, "trajectory_format")
        c.done()


@dataclass(frozen=True)
class SystemConfig:
    """The whole system (mgso.system): odometry + mapper, modes, evaluation of `mgso run` (docs/mgso.md)."""

    mode: Literal["deterministic", "realtime"] = opt(
        "deterministic", "deterministic: frames in order, a fixed number of mapping steps per keyframe, the same "
                         "result on every CPU run (tests, evaluation); realtime: the mapper trains in a process of its "
                         "own (system.mapper_process) while the odometry runs, a recorded sequence plays at its frame "
                         "rate and frames that arrive while the odometry is busy are dropped (as a live camera's)")
    playback_speed: float = opt(1.0, "realtime mode: a recorded sequence plays at this multiple of its frame rate "
                                     "(0 = as fast as the odometry takes frames, nothing dropped)")
    max_lag_ms: float = opt(250.0, "realtime mode: frames that arrive while the odometry is busy wait, in order, "
                                   "until they are this old (ms), then are dropped: the frames of a short stall (a "
                                   "keyframe's hand-over, DSO's motion-hypothesis search) are tracked late instead of "
                                   "lost; 0 = only the newest frame waits (every pose as fresh as it can be, the "
                                   "stalls' frames dropped)")
    odometry_map_thread: bool = opt(True, "realtime mode: the odometry's mapping half (window optimisation, "
                                          "marginalisation, new points) on a thread of its own beside the tracking, "
                                          "as DSO's mapping thread, so that a keyframe does not stall the frames "
                                          "behind it (docs/tracking.md); the deterministic mode runs the halves in "
                                          "order")
    mapper_lead: int | None = opt(None, "deterministic mode: keyframes the odometry may run ahead of the mapper, "
                                        "which applies the messages and trains in a thread of its own meanwhile "
                                        "(the same map bit for bit: it depends only on the messages and their "
                                        "order); 0 = the mapper in the odometry's thread after each frame; null = 4 "
                                        "with the map on the CPU, 0 on CUDA (not measured there yet)")
    mapper_process: bool = opt(True, "realtime mode: the mapper runs in a spawned process of its own (its own "
                                     "interpreter lock, Warp context and CUDA stream; keyframe images through shared "
                                     "memory); false: a thread of the odometry's process")
    odometry_threads: int = opt(0, "realtime mode with mapper_process: CPU threads of the odometry's kernel launches; "
                                   "0 = the cores the mapper does not take (at least 1)")
    mapper_threads: int = opt(0, "realtime mode with mapper_process: CPU threads of the mapper's kernel launches; "
                                 "0 = half the cores (at least 1)")
    mapper_nice: int = opt(5, "realtime mode with mapper_process (POSIX): the mapper process's niceness increment, "
                              "so that when the cores are short the odometry's frames come first and the map trains "
                              "in what is left (loop closure's thread gets the same increment, on Linux); 0 = same priority")
    mapper_sched_idle: bool = opt(True, "realtime mode with mapper_process (Linux): the mapper's process runs under "
                                        "the SCHED_IDLE policy while the camera runs, on the cores the odometry "
                                        "leaves: the scheduler then hands the tracking thread a core the mapper holds "
                                        "at once, which a niceness does not (docs/mgso.md); back to normal for the "
                                        "final refinement where the system allows it; false: mapper_nice alone")
    image_slots: int = opt(8, "realtime mode with mapper_process: keyframe images a block of the shared-memory ring "
                              "to the mapper process holds; when every slot waits for the mapper the ring grows by a "
                              "block (up to mapping.mapper.queue_size slots; beyond that the odometry waits, counted)")
    eval_monogs: bool = opt(True, "PSNR / SSIM at the tracked poses on every 5th frame, keyframes excluded (MonoGS "
                                  "protocol), when the run ends")
    eval_photo_slam: bool = opt(True, "PSNR / SSIM at the tracked poses on every tracked frame (Photo-SLAM protocol); "
                                      "one render per frame")
    eval_exposure: bool = opt(True, "evaluation renders get the frame's exposure from the odometry (DSO's affine "
                                    "(a, b) and exposure time), as keyframes do in training; false = the map's "
                                    "radiance as is")
    renders_side_by_side: bool = opt(True, "renders/NNNNNN.png holds input | render side by side; false = two files "
                                           "(renders/ and gt/) as 3DGS writes them")

    def __post_init__(self):
        c = _Checks("system", self)
        c.one_of(("deterministic", "realtime"), "mode")
        c.ge(0, "playback_speed", "max_lag_ms")
        c.ge(0, "odometry_threads", "mapper_threads")
        c.rule(self.mapper_lead is None or self.mapper_lead >= 0, "mapper_lead", ">= 0 or null")
        c.within(0, 19, "mapper_nice")
        c.ge(1, "image_slots")
        c.done()


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure (mgso.loop, docs/loop.md): place recognition on keyframes, Sim(3) verification, a Sim(3) pose
    graph over all keyframes, and the map moved with the corrected keyframes."""

    enabled: bool = opt(True, "detect revisits, correct the trajectory by a Sim(3) pose graph and move the Gaussian "
                              "map with it (false: DSO's odometry alone)")
    orb_features: int = opt(1000, "ORB descriptors of a keyframe at its most corner-like DSO points (LDSO: each with "
                                  "its depth), plus up to half as many of OpenCV's own corners where no chosen point "
                                  "is near (those borrow the depth of a DSO point within depth_radius_px)")
    depth_radius_px: float = opt(2.0, "a keypoint takes the inverse depth of the nearest DSO point within this many "
                                      "pixels (LDSO puts its features on DSO's points); farther ones have no depth")
    min_keyframe_gap: int = opt(15, "keyframes this recent (the active window, 7, and its neighbours) are never loop "
                                    "candidates: they are the odometry's own business")
    max_candidates: int = opt(3, "candidates verified per keyframe, best appearance first")
    prefilter_above: int = opt(20, "stored keyframes beyond which a bag of binary words learned from the sequence "
                                   "picks which are matched exactly (exact matching costs 3-6 ms a stored keyframe: "
                                   "the closer's time on 7-Scenes 13.4 s with 60, 8.8 s with 20 and keep 10, "
                                   "docs/loop.md); 0 = always exact")
    prefilter_keep: int = opt(10, "keyframes the bag-of-words prefilter keeps for exact matching (30: the same first "
                                  "candidate as exact matching in 35 of 36 7-Scenes queries; 10: the same loops on "
                                  "the synthetic loop, a third of the matching)")
    vocabulary_words: int = opt(512, "binary words of the prefilter's vocabulary, learned from the running sequence "
                                     "(nothing downloaded)")
    proximity_depths: float = opt(0.2, "old keyframes whose corrected camera is within this x the new keyframe's "
                                       "median depth (and looks within 60 degrees of its direction) are candidates "
                                       "whatever their appearance score; 0 = appearance only")
    min_matches: int = opt(40, "ratio-test ORB matches for a keyframe to be a candidate by appearance")
    match_ratio: float = opt(0.75, "Lowe's ratio test on Hamming distances (best < ratio x second best)")
    geometry: str = opt("current", "where verification takes 3D points from: current = the new keyframe's alone, PnP "
                                   "RANSAC on its points seen in the old keyframe's image, the old keyframe's depths "
                                   "only for the scale (ORB-SLAM's habit: the old side's depths are the loosest; on "
                                   "the out-and-back 7-Scenes recording it closes 55 loops, ATE 0.554 -> 0.240 m, "
                                   "docs/loop.md); both = the two keyframes' DSO depths, Sim(3) RANSAC on 3D-3D "
                                   "pairs (LDSO; closes none there)")
    epipolar_check: bool = opt(True, "geometry current: the candidate's matches, with a depth or not, must agree with "
                                     "one rigid motion (an essential matrix, RANSAC, min_inliers of them within "
                                     "inlier_px of their epipolar lines) before PnP, which then needs only "
                                     "min_pnp_inliers of those with a new keyframe's depth: the matches that carry a "
                                     "depth (descriptors at DSO's points) are the fewest right ones at a new viewpoint "
                                     "(freiburg1_rpy at 5-18 degrees: 4 of 24 right, against 20 right among the "
                                     "corners' matches without one; docs/loop.md); false = PnP on the matches with a depth alone, "
                                     "min_inliers of them")
    min_pnp_inliers: int = opt(20, "with the epipolar check: the PnP inliers among its inliers with a new keyframe's "
                                   "depth (the initial pose and the scale for the photometric check; ORB-SLAM's Sim3 "
                                   "needs 20). 10 accepts more on freiburg1_rpy, among them two loops of 11 inliers "
                                   "at its scale-collapsed start that cost its map 2.1 dB (docs/loop.md)")
    ransac_iterations: int = opt(300, "RANSAC hypotheses per candidate (3 point pairs each for Sim(3), 4 points for "
                                      "PnP)")
    inlier_px: float = opt(3.0, "a match is an inlier when it reprojects within this many pixels in both keyframes "
                                "(ORB-SLAM's Sim3Solver habit; level-0 pixels)")
    min_inliers: int = opt(30, "RANSAC inliers for a candidate to go on to the photometric check (ORB-SLAM accepts "
                               "20 after Sim3 RANSAC; wrong loops are worse than none)")
    max_photometric_rmse: float = opt(12.0, "the photometric check: DSO's residual RMSE (0-255 intensities, Huber "
                                            "weighted) of the candidate's points tracked into the new keyframe from "
                                            "the RANSAC pose must end below this (DSO's own tracking of a good frame "
                                            "is 5-10), else the candidate is rejected")
    min_photometric_inliers: float = opt(0.5, "... and at least this fraction of the candidate's points must be "
                                              "within the tracker's cutoff")
    depth_tolerance: float = opt(0.15, "the depth check: a current keyframe's DSO point, moved by the verified pose "
                                       "into the candidate, agrees with the candidate's depth map within this "
                                       "relative inverse depth")
    min_depth_consistent: float = opt(0.0, "... and at least this fraction of the points compared must agree (true "
                                           "views with good depths 0.95-0.98, a photograph of the place 0.41-0.54; "
                                           "but a real revisit's old depths are loose, and 0.75 refused all 137 true "
                                           "revisits of the out-and-back recording: docs/loop.md); 0 = off, the "
                                           "default: the planar check refuses photographs")
    min_depth_compared: int = opt(30, "... out of at least this many points compared; 0 = off")
    planar_fraction: float = opt(0.8, "the planar check: an old keyframe with at least this fraction of its DSO "
                                      "points on one plane (within 2 % of their depth) is a photograph of the new "
                                      "keyframe's view when the new keyframe's own points are not (below the same "
                                      "fraction): rejected (a photograph 0.98-1.0, views of a room 0.3-0.5, the "
                                      "out-and-back recording's verified revisits 0.13-0.42: docs/loop.md); 0 = off")
    realtime_cpu_share: float = opt(0.1, "real time: the closer's thread works at most this share of one core (it "
                                         "rests in between); of the keyframes that arrive meanwhile only the newest "
                                         "is searched and stored, so the tracking keeps its cores (7-Scenes at 2 cores: "
                                         "tracking 40.2-40.6 frames/s with 0.1 against 36.5-41.2 off, 31-34 with no "
                                         "rest: docs/loop.md); 1 = no rest")
    odometry_neighbours: int = opt(3, "odometry edges join each keyframe to this many previous ones (their relative "
                                      "poses from the window's estimate, which is what the window measured)")
    loop_edge_weight: float = opt(1.0, "information of a loop edge relative to an odometry edge (identity "
                                       "information for both, as LDSO's pose graph)")
    graph_iterations: int = opt(50, "Levenberg-Marquardt iterations of the pose graph (GTSAM)")

    def __post_init__(self):
        c = _Checks("loop", self)
        c.ge(4, "min_pnp_inliers")
        c.ge(1, "orb_features", "max_candidates", "ransac_iterations", "odometry_neighbours", "graph_iterations",
             "prefilter_keep", "vocabulary_words")
        c.ge(0, "prefilter_above", "min_depth_compared")
        c.within(0, 1, "min_depth_consistent", "planar_fraction")
        c.within(0, 1, "realtime_cpu_share", open_lo=True)
        c.gt(0, "depth_tolerance")
        c.ge(3, "min_inliers")
        c.ge(0, "min_keyframe_gap", "min_matches", "proximity_depths")
        c.one_of(("both", "current"), "geometry")
        c.gt(0, "depth_radius_px", "inlier_px", "max_photometric_rmse", "loop_edge_weight")
        c.within(0, 1, "match_ratio", "min_photometric_inliers", open_lo=True)
        c.done()


@dataclass(frozen=True)
class Config:
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    input: InputConfig = field(default_factory=InputConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    system: SystemConfig = field(default_factory=SystemConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)


# ---------------------------------------------------------------------------------------------- conversion
def _type_hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping for section {tp.__name__}, got {value!r}")
        return _build(tp, value, where)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str):  # YAML 1.1 reads 1e12 (no dot) as a string: take it as the number it means
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(f"{where}: expected a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin is typing.Union or origin is types.UnionType:
        for a in typing.get_args(tp):
            if a is type(None) and value is None:
                return None
        for a in typing.get_args(tp):
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError:
                pass
        raise ConfigError(f"{where}: {value!r} does not fit {tp}")
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"{where}: expected one of {typing.get_args(tp)}, got {value!r}")
        return value
    return value


def _child(where: str, key: str) -> str:
    """``file: section.key`` (the source once, then the dotted path that --set also uses)."""
    return f"{where}.{key}" if ": " in where else f"{where}: {key}"


def _build(cls, data: Mapping[str, Any], where: str):
    hints = _type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} in section {cls.__name__}; known: {sorted(names)}")
    kwargs, problems = {}, []
    for k, v in data.items():
        try:
            kwargs[k] = _coerce(v, hints[k], _child(where, k))
        except _RangeError as exc:  # the other sections are still checked: every range problem in one message
            problems.append(str(exc))
    if problems:
        raise _RangeError("; ".join(problems))
    return cls(**kwargs)


def config_from_dict(data: Mapping[str, Any], where: str = "config") -> Config:
    """Build a :class:`Config` from a nested mapping, checking every key, type and range."""
    try:
        return _build(Config, data, where)
    except _RangeError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def check_runtime(cfg: Config) -> None:
    """What only Warp can tell about a configuration: that the CUDA device ``runtime.device`` and
    ``runtime.odometry_device`` name is present. Raises :class:`ConfigError` naming the setting. Call it right after
    building the configuration (the form of both settings is checked when it is built). Costs nothing for ``cpu``,
    ``auto`` and an empty ``odometry_device``: Warp is imported (and started) only for a ``cuda`` name."""
    for key in ("device", "odometry_device"):
        value = getattr(cfg.runtime, key)
        name = value.strip().lower()
        if not name.startswith("cuda"):
            continue
        from mgso_kernels import runtime  # lazily: starting Warp takes a second

        count = runtime.cuda_device_count()
        index = int(name.split(":", 1)[1]) if ":" in name else 0
        if count == 0:
            raise ConfigError(f"runtime.{key} is {value!r}, but Warp sees no CUDA device on this machine; "
                              "use cpu (or auto: CUDA when present, else the CPU)")
        if index >= count:
            raise ConfigError(f"runtime.{key} is {value!r}, but this machine has {count} CUDA device(s): "
                              f"cuda:0 to cuda:{count - 1}")


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Nested plain dict (tuples become lists) suitable for YAML/JSON."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = config_to_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def _deep_merge(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def available_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILE_DIR.glob("*.yaml"))


def _resolve_profile(name_or_path: str | Path, relative_to: Path | None) -> Path:
    p = Path(name_or_path).expanduser()
    candidates = []
    if p.suffix in (".yaml", ".yml"):
        if not p.is_absolute() and relative_to is not None:
            candidates.append(relative_to / p)
        candidates.append(p)
    else:
        candidates.append(PROFILE_DIR / f"{p}.yaml")
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise ConfigError(f"config profile {str(name_or_path)!r} not found (looked at {[str(c) for c in candidates]}; "
                      f"built-in profiles: {available_profiles()})")


def _load_yaml_chain(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    if path in seen:
        raise ConfigError(f"{path}: inherit_from makes a cycle: {' -> '.join(str(s) for s in seen + (path,))}")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    data = dict(data)
    parent = data.pop("inherit_from", None)
    if parent is None:
        return data
    if not isinstance(parent, str) or not parent.strip():
        raise ConfigError(f"{path}: inherit_from must be a profile name or a .yaml path, "
                          f"got {type(parent).__name__} {parent!r}")
    parent_path = _resolve_profile(parent, path.parent)
    return _deep_merge(_load_yaml_chain(parent_path, seen + (path,)), data)


def _parse_override(item: str) -> tuple[list[str], Any]:
    if "=" not in item:
        raise ConfigError(f"override {item!r}: expected section.key=value")
    key, raw = item.split("=", 1)
    keys = [k for k in key.strip().split(".") if k]
    if len(keys) < 2:
        raise ConfigError(f"override {item!r}: expected section.key=value (e.g. tracking.pyramid_levels=5)")
    try:
        value = yaml.safe_load(raw) if raw.strip() != "" else ""
    except yaml.YAMLError:
        value = raw
    return keys, value


def apply_overrides(cfg: Config, overrides: Sequence[str]) -> Config:
    """Return a copy of ``cfg`` with dotted ``section.key=value`` overrides applied and type-checked."""
    data = config_to_dict(cfg)
    for item in overrides:
        keys, value = _parse_override(item)
        node = data
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                raise ConfigError(f"override {item!r}: no section {k!r}")
            node = node[k]
        if keys[-1] not in node:
            raise ConfigError(f"override {item!r}: unknown key {keys[-1]!r}; known: {sorted(node)}")
        node[keys[-1]] = value
    return config_from_dict(data, where="override")


def load_config(profile: str | Path | None = None, overrides: Sequence[str] = ()) -> Config:
    """Defaults, then a profile (built-in name or YAML path, with inheritance), then dotted overrides."""
    cfg = Config()
    if profile is not None:
        path = _resolve_profile(profile, None)
        cfg = config_from_dict(_load_yaml_chain(path), where=str(path))
    return apply_overrides(cfg, overrides) if overrides else cfg


def save_config(cfg: Config, path: str | Path) -> None:
    """Write the full resolved configuration (every field) as YAML."""
    Path(path).write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))


def describe_config(cfg: Any, prefix: str = "") -> list[str]:
    """Lines ``section.key = value  # reason`` for every field."""
    lines = []
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(v):
            lines.extend(describe_config(v, name + "."))
        else:
            reason = f.metadata.get("reason", "")
            lines.append(f"{name} = {v!r}" + (f"  # {reason}" if reason else ""))
    return lines
