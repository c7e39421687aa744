"""Collect evaluation results into one JSON file and a short text summary (what ``mgso eval`` writes and prints).

Every figure keeps its qualifiers next to it: ATE says its alignment and which poses (the result's ``label``, e.g.
"all frames" / "keyframes"), rendering figures say their protocol and SSIM border.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable

from .ate import AteResult, RpeResult
from .render_metrics import RenderMetrics

__all__ = ["metrics_report", "write_metrics_json", "format_report"]


def _listify(x) -> list:
    if x is None:
        return []
    if isinstance(x, (AteResult, RpeResult, RenderMetrics)):
        return [x]
    return list(x)


def _json_safe(x: Any) -> Any:
    """Non-finite floats (a PSNR of identical images is inf) become None: strict JSON has no inf / nan."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def metrics_report(*, ate: AteResult | Iterable[AteResult] | None = None,
                   rpe: RpeResult | Iterable[RpeResult] | None = None,
                   renders: RenderMetrics | Iterable[RenderMetrics] | None = None,
                   extra: dict | None = None) -> dict:
    """A JSON-ready dict: ``{"ate": [...], "rpe": [...], "render": [...], **extra}`` (each result's ``as_dict()``,
    non-finite numbers as null)."""
    out: dict[str, Any] = {
        "ate": [r.as_dict() for r in _listify(ate)],
        "rpe": [r.as_dict() for r in _listify(rpe)],
        "render": [r.as_dict() for r in _listify(renders)],
    }
    if extra:
        clash = set(extra) & set(out)
        if clash:
            raise ValueError(f"metrics_report: extra keys {sorted(clash)} clash with the result sections")
        out.update(extra)
    return _json_safe(out)


def write_metrics_json(path: str | Path, **kwargs) -> Path:
    """Write :func:`metrics_report` (same keyword arguments) as indented, strict JSON; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(metrics_report(**kwargs), fh, indent=2, allow_nan=False)
        fh.write("\n")
    return path


def format_report(*, ate=None, rpe=None, renders=None) -> str:
    """One line per result (their ``summary()``), ATE first; an ATE's warnings (``AteResult.warnings``) each on a
    line of its own after it."""
    lines = [line for r in _listify(ate) for line in [r.summary()] + [f"WARNING: {w}" for w in r.warnings()]]
    lines += [r.summary() for r in _listify(rpe)]
    lines += [r.summary() for r in _listify(renders)]
    return "\n".join(lines)
