"""The benchmark spec of ``mgso bench`` (docs/bench.md): a YAML file naming sequences, variants and seeds, read and
checked whole before any task starts, and expanded into one :class:`Task` per (sequence, variant, seed).

Every problem is one :class:`SpecError` line naming the file and the entry (``SPEC: variants.fast.set[1]: ...``):
bad YAML, an unknown key, a sequence that is not there or whose layout is not recognised, a setting that
:func:`mgso.config.load_config` refuses (the same checks as ``--set``).
"""

from __future__ import annotations

import glob as globmod
import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mgso.config import ConfigError, config_to_dict, load_config

__all__ = ["SpecError", "SequenceEntry", "Variant", "Task", "BenchSpec", "load_spec", "builtin_specs",
           "resolve_spec_path", "BUILTIN_DIR"]

BUILTIN_DIR = Path(__file__).resolve().parents[1] / "configs" / "bench"

TOP_KEYS = ("name", "description", "data_root", "stage", "seeds", "repeats", "resources", "sequences", "variants",
            "reference_dso")
DSO_KEYS = ("binary", "nomt", "name", "resources")
#: The reference DSO's script (profiles/dso_reference.py of an mgso checkout: not installed with the package).
DSO_SCRIPT = Path(__file__).resolve().parents[2] / "profiles" / "dso_reference.py"
DSO_STAGE = "dso"
SEQ_KEYS = ("path", "glob", "name", "calib", "groundtruth")
VARIANT_KEYS = ("config", "set", "stage", "resources", "description")
RESOURCE_KEYS = ("num_cpus", "num_gpus")


class SpecError(ConfigError):
    """A benchmark spec that cannot be run; the message (one line) names the file and the entry. A
    :class:`~mgso.config.ConfigError`, so that the CLI prints it as one line however it was started (``python -m
    mgso.app.cli`` has its own ``CliError`` class)."""


@dataclass(frozen=True)
class SequenceEntry:
    name: str
    path: Path
    calib: str | None = None
    groundtruth: str | None = None


@dataclass(frozen=True)
class Variant:
    name: str
    stage: str
    config: str | None = None
    sets: tuple[str, ...] = ()
    num_cpus: float = 1.0
    num_gpus: float = 0.0


@dataclass(frozen=True)
class Task:
    """One ``mgso run`` of (sequence, variant, seed). ``key``: the hash of its inputs (the sequence, the stage and
    the whole resolved configuration), the name of its run folder under ``DIR/runs/``."""

    sequence: str
    variant: str
    seed: int
    stage: str
    path: str
    calib: str | None
    groundtruth: str | None
    config: str | None
    sets: tuple[str, ...]
    num_cpus: float
    num_gpus: float
    key: str
    dso_binary: str | None = None     # the reference DSO row (stage "dso"): profiles/dso_reference.py runs it
    dso_nomt: bool = False

    def dso_args(self) -> list[str]:
        """The reference DSO row's command (after ``python``)."""
        return [str(DSO_SCRIPT), "--dso", str(self.dso_binary), "--path", self.path] + (
            ["--nomt"] if self.dso_nomt else [])

    def run_args(self, out: str | os.PathLike) -> list[str]:
        """The arguments of the ``mgso run`` this task is (after ``mgso``)."""
        args = ["run", self.path, "--out", str(out), "--stage", self.stage]
        if self.calib:
            args += ["--calib", self.calib]
        if self.groundtruth:
            args += ["--groundtruth", self.groundtruth]
        if self.config:
            args += ["--config", self.config]
        for s in self.sets:
            args += ["--set", s]
        return args

    def command(self, out: str | os.PathLike) -> str:
        """The same run as one shell command line (the ``command`` column of results.csv)."""
        import shlex

        if self.stage == DSO_STAGE:
            return "python " + " ".join(shlex.quote(a) for a in self.dso_args())
        return "mgso " + " ".join(shlex.quote(a) for a in self.run_args(out))

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class BenchSpec:
    path: Path
    name: str
    sequences: list[SequenceEntry]
    variants: list[Variant]
    seeds: list[int]
    text: str = ""
    tasks: list[Task] = field(default_factory=list)


def builtin_specs() -> list[str]:
    return sorted(p.stem for p in BUILTIN_DIR.glob("*.yaml"))


def resolve_spec_path(name_or_path: str | os.PathLike) -> Path:
    """A spec file, or the name of a built-in spec (``mgso/configs/bench/NAME.yaml``)."""
    p = Path(name_or_path).expanduser()
    if p.is_file():
        return p
    if p.is_dir():
        raise SpecError(f"{name_or_path}: is a folder, not a spec file (give a YAML file or a built-in name: "
                        f"{', '.join(builtin_specs()) or 'none'})")
    if p.suffix not in (".yaml", ".yml") and (BUILTIN_DIR / f"{p}.yaml").is_file():
        return BUILTIN_DIR / f"{p}.yaml"
    raise SpecError(f"{name_or_path}: no such spec file (built-in specs: {', '.join(builtin_specs()) or 'none'})")


def _one_line(text: str) -> str:
    return re.sub(r"\s*\n\s*", " ", str(text)).strip()


def _check_keys(where: str, data: dict, known: tuple[str, ...]) -> None:
    unknown = [k for k in data if k not in known]
    if unknown:
        raise SpecError(f"{where}: unknown key {unknown[0]!r}; known: {', '.join(known)}")


def _resources(where: str, data: Any, base: tuple[float, float]) -> tuple[float, float]:
    if data is None:
        return base
    if not isinstance(data, dict):
        raise SpecError(f"{where}: expected a mapping (num_cpus, num_gpus), got {data!r}")
    _check_keys(where, data, RESOURCE_KEYS)
    cpus, gpus = base
    for k, v in data.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise SpecError(f"{where}.{k}: expected a number >= 0, got {v!r}")
    cpus = float(data.get("num_cpus", cpus))
    gpus = float(data.get("num_gpus", gpus))
    if cpus <= 0:
        raise SpecError(f"{where}.num_cpus: a task needs at least a part of a CPU, got {cpus:g}")
    return cpus, gpus


def _data_root(spec_path: Path, raw: Any) -> Path:
    where = f"{spec_path}: data_root"
    if raw is None:
        return spec_path.parent
    if not isinstance(raw, str):
        raise SpecError(f"{where}: expected a folder or 'shared', got {raw!r}")
    if raw == "shared":
        from mgso.io.paths import shared_data_dir

        root = shared_data_dir()
        if root is None:
            raise SpecError(f"{where}: 'shared': the shared recordings were not found (set MGSO_DATA to their folder, "
                            "or place them in ../shared/data)")
        return root
    root = Path(os.path.expandvars(raw)).expanduser()
    root = root if root.is_absolute() else spec_path.parent / root
    if not root.is_dir():
        raise SpecError(f"{where}: {raw!r}: no such folder ({root})")
    return root


def _sequences(spec_path: Path, raw: Any, root: Path) -> list[SequenceEntry]:
    from mgso.io import DatasetError, open_sequence
    from mgso.io.calibration import inline_intrinsics

    where = f"{spec_path}: sequences"
    if not isinstance(raw, list) or not raw:
        raise SpecError(f"{where}: expected a list of sequences (paths, globs or mappings with path/glob)")
    out: list[SequenceEntry] = []
    for i, item in enumerate(raw):
        w = f"{where}[{i}]"
        if isinstance(item, str):
            item = {"glob" if any(c in item for c in "*?[") else "path": item}
        if not isinstance(item, dict):
            raise SpecError(f"{w}: expected a path, a glob or a mapping, got {item!r}")
        _check_keys(w, item, SEQ_KEYS)
        if ("path" in item) == ("glob" in item):
            raise SpecError(f"{w}: give exactly one of path and glob")

        def rel(p: str) -> Path:
            q = Path(os.path.expandvars(str(p))).expanduser()
            return q if q.is_absolute() else root / q

        if "path" in item:
            p = rel(item["path"])
            if not p.exists():
                raise SpecError(f"{w}: {item['path']!r}: unknown sequence: no such file or folder ({p})")
            paths = [p]
        else:
            paths = [Path(p) for p in sorted(globmod.glob(str(rel(item["glob"]))))]
            if not paths:
                raise SpecError(f"{w}: glob {item['glob']!r} matches nothing (under {root})")
            if "name" in item:
                raise SpecError(f"{w}: a glob's sequences are named by their folders; 'name' is for one path")
        extra = {}
        for k in ("calib", "groundtruth"):
            if item.get(k) is not None:
                if k == "calib" and inline_intrinsics(str(item[k])) and not rel(item[k]).is_file():
                    extra[k] = str(item[k])     # the intrinsics themselves, 'fx fy cx cy [k1 k2 p1 p2 [k3]]'
                    continue
                f = rel(item[k])
                if not f.is_file():
                    raise SpecError(f"{w}.{k}: {item[k]!r}: no such file ({f})")
                extra[k] = str(f.resolve())
        for p in paths:
            name = str(item.get("name") or p.name)
            try:   # the layout is recognised and the calibration found: what `mgso info` checks, no frame decoded
                open_sequence(p, calib=extra.get("calib"), groundtruth=extra.get("groundtruth"))
            except (DatasetError, OSError, ValueError) as exc:
                raise SpecError(f"{w}: {p}: {_one_line(exc)}") from None
            except Exception as exc:  # noqa: BLE001 - a calibration error and the like: still one line
                raise SpecError(f"{w}: {p}: {_one_line(exc)}") from None
            if any(s.name == name for s in out):
                raise SpecError(f"{w}: a second sequence named {name!r} (give each a 'name')")
            out.append(SequenceEntry(name, p.resolve(), extra.get("calib"), extra.get("groundtruth")))
    return out


def _sets(where: str, raw: Any) -> list[str]:
    if raw is None:
        return []
    if isinstance(raw, dict):       # {section.key: value}
        return [f"{k}={yaml.safe_dump(v, default_flow_style=True).strip().removesuffix('...').strip()}"
                for k, v in raw.items()]
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or not all(isinstance(s, str) for s in raw):
        raise SpecError(f"{where}: expected a list of 'section.key=value' settings, got {raw!r}")
    return list(raw)


def _variants(spec_path: Path, raw: Any, stage: str, res: tuple[float, float], seed0: int) -> list[Variant]:
    from .stages import STAGES

    where = f"{spec_path}: variants"
    if raw is None:
        raw = {"default": {}}
    if not isinstance(raw, dict) or not raw:
        raise SpecError(f"{where}: expected a mapping of variant names to settings")
    out = []
    for name, body in raw.items():
        w = f"{where}.{name}"
        body = body or {}
        if not isinstance(body, dict):
            raise SpecError(f"{w}: expected a mapping (config, set, stage, resources), got {body!r}")
        _check_keys(w, body, VARIANT_KEYS)
        st = body.get("stage", stage)
        if st not in STAGES:
            raise SpecError(f"{w}.stage: unknown stage {st!r}; available: {', '.join(STAGES)}")
        sets = _sets(f"{w}.set", body.get("set"))
        profile = body.get("config")
        if profile is not None and not isinstance(profile, str):
            raise SpecError(f"{w}.config: expected a profile name or YAML file, got {profile!r}")
        if profile is not None and profile.endswith((".yaml", ".yml")) and not Path(profile).is_absolute():
            profile = str((spec_path.parent / profile).resolve())
        try:
            load_config(profile, sets)       # the whole variant first: a bad profile is named as such
        except ConfigError as exc:
            for j, s in enumerate(sets):     # name the entry that is refused
                try:
                    load_config(None, [s])
                except ConfigError as one:
                    raise SpecError(f"{w}.set[{j}]: {_one_line(one)}") from None
            raise SpecError(f"{w}: {_one_line(exc)}") from None
        cpus, gpus = _resources(f"{w}.resources", body.get("resources"), res)
        out.append(Variant(str(name), st, profile, tuple(sets), cpus, gpus))
    return out


def _seeds(spec_path: Path, data: dict) -> list[int]:
    if "seeds" in data and "repeats" in data:
        raise SpecError(f"{spec_path}: give seeds or repeats, not both")
    if "repeats" in data:
        r = data["repeats"]
        if isinstance(r, bool) or not isinstance(r, int) or r < 1:
            raise SpecError(f"{spec_path}: repeats: expected an integer >= 1, got {r!r}")
        return list(range(r))
    s = data.get("seeds", [0])
    if isinstance(s, int) and not isinstance(s, bool):
        s = [s]
    if (not isinstance(s, list) or not s or any(isinstance(x, bool) or not isinstance(x, int) or x < 0 for x in s)
            or len(set(s)) != len(s)):
        raise SpecError(f"{spec_path}: seeds: expected a list of distinct integers >= 0, got {s!r}")
    return s


def _reference_dso(spec_path: Path, raw: Any, res: tuple[float, float]) -> tuple[str, str, bool, float] | None:
    """``reference_dso: {binary: PATH, nomt: false, name: dso-reference}``: the reference DSO as another row."""
    where = f"{spec_path}: reference_dso"
    if raw is None:
        return None
    if not isinstance(raw, dict) or "binary" not in raw:
        raise SpecError(f"{where}: expected a mapping with binary: the path of DSO's dso_dataset")
    _check_keys(where, raw, DSO_KEYS)
    b = Path(os.path.expandvars(str(raw["binary"]))).expanduser()
    b = b if b.is_absolute() else spec_path.parent / b
    if not (b.is_file() and os.access(b, os.X_OK)):
        raise SpecError(f"{where}.binary: {raw['binary']!r}: not an executable file ({b})")
    if not DSO_SCRIPT.is_file():
        raise SpecError(f"{where}: needs {DSO_SCRIPT.name} from the profiles/ folder of an mgso checkout (it is not "
                        "installed with the package)")
    if not isinstance(raw.get("nomt", False), bool):
        raise SpecError(f"{where}.nomt: expected true/false, got {raw['nomt']!r}")
    cpus, _ = _resources(f"{where}.resources", raw.get("resources"), res)
    return str(raw.get("name") or "dso-reference"), str(b.resolve()), bool(raw.get("nomt", False)), cpus


def task_key(path: str, calib: str | None, groundtruth: str | None, stage: str, config: dict) -> str:
    blob = json.dumps({"path": path, "calib": calib, "groundtruth": groundtruth, "stage": stage, "config": config},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def load_spec(name_or_path: str | os.PathLike) -> BenchSpec:
    """Read and check a spec (see the module doc); its :attr:`BenchSpec.tasks` are every (sequence, variant, seed),
    sequence-major. Raises :class:`SpecError` (one line) on any problem."""
    from .stages import DEFAULT_STAGE, STAGES

    path = resolve_spec_path(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        raise SpecError(f"{path}: not valid YAML{at}: {_one_line(getattr(exc, 'problem', None) or exc)}") from None
    if not isinstance(data, dict):
        raise SpecError(f"{path}: expected a mapping at the top level (sequences, variants, seeds, ...)")
    _check_keys(str(path), data, TOP_KEYS)
    stage = data.get("stage", DEFAULT_STAGE)
    if stage not in STAGES:
        raise SpecError(f"{path}: stage: unknown stage {stage!r}; available: {', '.join(STAGES)}")
    seeds = _seeds(path, data)
    res = _resources(f"{path}: resources", data.get("resources"), (1.0, 0.0))
    variants = _variants(path, data.get("variants"), stage, res, seeds[0])
    dso = _reference_dso(path, data.get("reference_dso"), res)
    if dso is not None and any(v.name == dso[0] for v in variants):
        raise SpecError(f"{path}: reference_dso.name: {dso[0]!r} is also a variant's name")
    root = _data_root(path, data.get("data_root"))
    seqs = _sequences(path, data.get("sequences"), root)
    spec = BenchSpec(path=path, name=str(data.get("name") or path.stem), sequences=seqs, variants=variants,
                     seeds=seeds, text=text)
    for s in seqs:
        for v in variants:
            for seed in seeds:
                sets = list(v.sets) + [f"runtime.seed={seed}"]
                if not any(x.split("=", 1)[0].strip() == "runtime.threads" for x in v.sets):
                    sets.append(f"runtime.threads={max(1, int(v.num_cpus))}")   # the CPUs the task declares
                cfg = load_config(v.config, sets)
                key = task_key(str(s.path), s.calib, s.groundtruth, v.stage, config_to_dict(cfg))
                spec.tasks.append(Task(s.name, v.name, seed, v.stage, str(s.path), s.calib, s.groundtruth, v.config,
                                       tuple(sets), v.num_cpus, v.num_gpus, key))
        for seed in (seeds if dso is not None else ()):   # the reference DSO on the same frames: one run a seed
            name, binary, nomt, cpus = dso                   # of the spec (its runs differ by its threads' timing)
            key = task_key(str(s.path), None, None, DSO_STAGE, {"binary": binary, "nomt": nomt, "run": seed})
            spec.tasks.append(Task(s.name, name, seed, DSO_STAGE, str(s.path), None, None, None, (), cpus, 0.0, key,
                                   binary, nomt))
    return spec
