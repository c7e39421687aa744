"""Typed configuration: frozen dataclasses, one section per subsystem, every default with a one-line reason.

- Defaults live here (``opt(default, "reason")``); the reason is kept in the field's metadata so that
  ``mgso info --config`` can print it.
- YAML profiles (``mgso/configs/*.yaml`` or any file) give a nested mapping of the fields they change and may name a
  parent with ``inherit_from: <profile name or path>`` (as MonoGS does).
- Dotted overrides from the command line: ``--set tracking.max_frames=7`` (value parsed as YAML, then checked
  against the field's type).

Unknown keys and wrong types are errors that name the file (or override) and the key; nothing is silently ignored.
Subsystems read their own section and get it as an argument; nothing reads global configuration.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml

__all__ = [
    "opt", "RuntimeConfig", "InputConfig", "TrackingConfig", "WindowConfig", "MappingConfig", "OutputConfig",
    "Config", "ConfigError", "load_config", "apply_overrides", "config_from_dict", "config_to_dict", "save_config",
    "describe_config", "PROFILE_DIR", "available_profiles",
]

PROFILE_DIR = Path(__file__).resolve().parent / "configs"


class ConfigError(ValueError):
    """A configuration file or override is wrong; the message names where and what."""


def opt(default: Any, reason: str) -> Any:
    """A dataclass field with a default and its one-line reason."""
    if isinstance(default, (list, dict, set)):
        raise TypeError("use tuples for sequence defaults so the config stays immutable")
    return field(default=default, metadata={"reason": reason})


# --------------------------------------------------------------------------------------------------- sections
@dataclass(frozen=True)
class RuntimeConfig:
    device: str = opt("auto", "Warp device: cpu, cuda, cuda:N, or auto (CUDA when present, else CPU)")
    threads: int = opt(0, "CPU threads for split kernel launches; 0 = all available cores")
    seed: int = opt(0, "seed of every random choice (pixel selection directions, random init), for repeatable runs")


@dataclass(frozen=True)
class InputConfig:
    """Reading frames (mgso.io): which frames, which camera, how to undistort (docs/datasets.md)."""

    start: int = opt(0, "first frame index used from the sequence")
    end: int = opt(0, "one past the last frame index used; 0 = to the end")
    stride: int = opt(1, "use every n-th frame (1 = every frame)")
    width: int = opt(0, "output (undistorted) image width; 0 = the calibration's output size")
    height: int = opt(0, "output (undistorted) image height; 0 = the calibration's output size")
    photometric: bool = opt(True, "apply photometric calibration (response, vignette, exposure) when present")
    rectify: str = opt("", "undistortion output: crop (no black border), full (whole input visible), none (input "
                           "intrinsics); empty = what the calibration file says (crop for a distorted lens if silent)")
    camera: str = opt("", "camera of a multi-camera layout (EuRoC cam0/cam1, KITTI image_0/image_2); empty = the "
                          "layout's first camera")
    fps: float = opt(30.0, "frame rate for timestamps when a layout has none (image folders without times.txt, "
                           "Replica)")
    prefetch: int = opt(2, "frames decoded ahead by a background thread while iterating (PNG decoding is a large "
                           "share of a frame's time); 0 = decode in the caller")
    gt_max_dt: float = opt(0.02, "largest time difference (s) when matching ground-truth poses to frames (TUM "
                                 "RGB-D, EuRoC, TUM monoVO: nearest pose within this)")


@dataclass(frozen=True)
class TrackingConfig:
    """DSO front end (filled in by the tracking work)."""

    pyramid_levels: int = opt(0, "pyramid levels; 0 = as many as keep the coarsest level >= ~30 px (DSO: 5-6)")


@dataclass(frozen=True)
class WindowConfig:
    """DSO sliding-window bundle adjustment."""

    max_frames: int = opt(7, "keyframes in the sliding window (DSO setting_maxFrames = 7)")


@dataclass(frozen=True)
class MappingConfig:
    """Gaussian splatting map and its training."""

    enabled: bool = opt(True, "build the Gaussian map (false = odometry only)")


@dataclass(frozen=True)
class OutputConfig:
    trajectory_format: str = opt("tum", "trajectory file format: tum (timestamp tx ty tz qx qy qz qw) or kitti")
    save_renders: bool = opt(True, "write renders of evaluation frames next to the input")
    plot: bool = opt(True, "write a trajectory plot when ground truth is present (needs matplotlib)")


@dataclass(frozen=True)
class Config:
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    input: InputConfig = field(default_factory=InputConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


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
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(args, value)))
    if origin is typing.Union or str(origin) == "types.UnionType":
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


def _build(cls, data: Mapping[str, Any], where: str):
    hints = _type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} in section {cls.__name__}; known: {sorted(names)}")
    kwargs = {k: _coerce(v, hints[k], f"{where}: {k}") for k, v in data.items()}
    return cls(**kwargs)


def config_from_dict(data: Mapping[str, Any], where: str = "config") -> Config:
    """Build a :class:`Config` from a nested mapping, checking every key and type."""
    return _build(Config, data, where)


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
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(data).__name__}")
    data = dict(data)
    parent = data.pop("inherit_from", None)
    if parent is None:
        return data
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
