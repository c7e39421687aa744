"""The table and the pictures of ``mgso bench`` (docs/bench.md): ``results.csv`` (a row per task),
``summary.md`` (median with min-max per sequence and variant, the winner of each column marked), ``ate.png`` and
``psnr.png``, and ``mgso bench --compare A.csv B.csv``.

Every file is written atomically (a temporary name, then ``os.replace``): a bench stopped while writing leaves the
previous complete table, never half of one.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Iterable

from .writer import atomic_path

__all__ = ["HEAD_COLUMNS", "FIGURES", "flatten_metrics", "headline", "write_results_csv", "read_results_csv",
           "summary_markdown", "write_plots", "compare_tables", "atomic_write_text"]

#: The columns every row starts with; then the headline figures (:data:`FIGURES`), then every figure of
#: metrics.json flattened (``metrics.<key>.<key>``).
HEAD_COLUMNS = ("sequence", "variant", "seed", "stage", "status", "exit_code", "error", "skipped", "run_dir", "key",
                "wall_s", "cpu_s", "host", "mgso_version", "commit", "python", "ray_version", "warp_version",
                "numpy_version", "num_cpus", "num_gpus", "command")

#: The headline figures: column -> (label, the metrics.json keys that hold it, in order of preference, better).
#: Every stage writes them at the top (one writer since issue 44); the ``tracking.*`` and ``dso.fps`` keys are
#: read from the results of older odometry and tracking runs and from the reference DSO's tasks.
FIGURES = {
    "ate_m": ("ATE all frames [m]", ("ate_all_frames_m", "tracking.ate_rmse_all_frames"), "lower"),
    # what the ATE is worth (docs/evaluation.md): the trajectory's scale drift (the reference DSO's on its
    # marginalised keyframes)
    "scale_drift": ("scale drift [x]", ("trajectory_check.scale_drift", "dso.scale_drift"), "lower"),
    "psnr_db": ("PSNR MonoGS [dB]", ("psnr_monogs_db",), "higher"),
    "ssim": ("SSIM MonoGS", ("ssim_monogs",), "higher"),
    "gaussians": ("Gaussians", ("num_gaussians",), "lower"),
    "map_mb": ("map [MB]", ("map_size_mb",), "lower"),
    "fps": ("frames/s end to end", ("end_to_end_fps", "tracking.fps", "dso.fps"), "higher"),
}


def atomic_write_text(path: Path, text: str) -> None:
    """``text`` to ``path`` atomically (:func:`mgso.app.writer.atomic_path`)."""
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="")


def flatten_metrics(metrics: dict | None, prefix: str = "") -> dict:
    """Every scalar of metrics.json as ``key.key`` -> value; short lists of numbers as JSON; lists of records (the
    ATE/render reports, whose headline figures are already scalars) and the protocols' prose are left out."""
    out: dict = {}
    for k, v in (metrics or {}).items():
        name = f"{prefix}{k}"
        if k in ("protocols", "written"):
            continue
        if isinstance(v, dict):
            out.update(flatten_metrics(v, name + "."))
        elif isinstance(v, list):
            if len(v) <= 8 and all(isinstance(x, (int, float, str)) or x is None for x in v):
                out[name] = json.dumps(v)
        else:
            out[name] = v
    return out


def headline(flat: dict) -> dict:
    """The :data:`FIGURES` of one task from its flattened metrics (``None`` when the stage has no such figure)."""
    out = {}
    for col, (_, keys, _) in FIGURES.items():
        out[col] = next((flat[k] for k in keys if flat.get(k) is not None), None)
    return out


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ""
    return str(v)


def write_results_csv(path: Path, rows: list[dict]) -> None:
    """One row per task: :data:`HEAD_COLUMNS`, the headline :data:`FIGURES`, then ``metrics.*`` (sorted)."""
    extra = sorted({k for r in rows for k in r if k.startswith("metrics.")})
    cols = list(HEAD_COLUMNS) + list(FIGURES) + extra
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in cols])
    atomic_write_text(path, buf.getvalue())


def read_results_csv(path: str | os.PathLike) -> list[dict]:
    """The rows of a results.csv (cells as strings); raises ValueError (one line) when it is not one."""
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"{p}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    if rows and not {"sequence", "variant", "status"} <= set(rows[0]):
        raise ValueError(f"{p}: not a results.csv of mgso bench (no sequence/variant/status columns)")
    if not rows:
        raise ValueError(f"{p}: no rows (an empty file or only a header): nothing to compare")
    return rows


def _num(v) -> float | None:
    if v is None or v == "":
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _median(xs: list[float]) -> float:
    s = sorted(xs)
    n = len(s)
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


def group_figures(rows: Iterable[dict]) -> dict:
    """(sequence, variant) -> column -> the values of the tasks that finished (status ok)."""
    groups: dict = {}
    for r in rows:
        g = groups.setdefault((r["sequence"], r["variant"]), {c: [] for c in FIGURES})
        if r.get("status") != "ok":
            continue
        for c in FIGURES:
            x = _num(r.get(c))
            if x is not None:
                g[c].append(x)
    return groups


def _fmt(x: float, col: str) -> str:
    if col == "gaussians":
        return f"{x:,.0f}"
    if col == "ate_m":
        return f"{x:.4f}"
    if col in ("ssim",):
        return f"{x:.4f}"
    return f"{x:.2f}"


def summary_markdown(rows: list[dict], title: str = "") -> str:
    """Per sequence and variant: the median with min-max of each headline figure over the finished tasks, the
    variant whose median wins each column in bold (lower ATE, scale drift, Gaussians and MB; higher PSNR, SSIM and
    frames/s),
    and how many tasks finished, failed or were not run."""
    groups = group_figures(rows)
    status: dict = {}
    for r in rows:
        status.setdefault((r["sequence"], r["variant"]), []).append(r.get("status", ""))
    lines = [f"# mgso bench: {title}" if title else "# mgso bench", ""]
    lines.append("Median (min-max) over the finished runs of each sequence and variant; **bold**: the variant whose "
                 "median wins the column on that sequence (lower ATE, scale drift, Gaussians and MB; higher PSNR, "
                 "SSIM and frames/s). The rows of results.csv hold every figure of every run.")
    lines.append("")
    cols = [c for c in FIGURES if any(g[c] for g in groups.values())]
    head = ["sequence", "variant", "runs"] + [FIGURES[c][0] for c in cols]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    seqs = list(dict.fromkeys(k[0] for k in groups))
    for s in seqs:
        keys = [k for k in groups if k[0] == s]
        best = {}
        for c in cols:
            meds = {k: _median(groups[k][c]) for k in keys if groups[k][c]}
            if len(meds) > 1:
                pick = min if FIGURES[c][2] == "lower" else max
                top = pick(meds.values())
                best[c] = {k for k, m in meds.items() if m == top}
        for k in keys:
            st = status[k]
            ok = st.count("ok")
            runs = f"{ok}/{len(st)}" + (f" ({len(st) - ok} not ok)" if ok < len(st) else "")
            cells = [s, k[1], runs]
            for c in cols:
                xs = groups[k][c]
                if not xs:
                    cells.append("-")
                    continue
                m = _fmt(_median(xs), c)
                cell = f"**{m}**" if k in best.get(c, ()) else m
                if len(xs) > 1:
                    cell += f" ({_fmt(min(xs), c)}-{_fmt(max(xs), c)})"
                cells.append(cell)
            lines.append("| " + " | ".join(cells) + " |")
    failed = [r for r in rows if r.get("status") not in ("ok",)]
    if failed:
        lines += ["", "Runs that did not finish:", ""]
        for r in failed:
            lines.append(f"- {r['sequence']} / {r['variant']} / seed {r.get('seed')}: {r.get('status')}"
                         + (f": {r['error']}" if r.get("error") else "") + f" ({r.get('run_dir', '')})")
    return "\n".join(lines) + "\n"


def write_plots(rows: list[dict], out_dir: Path) -> list[Path]:
    """``ate.png`` and ``psnr.png``: per sequence, each variant's runs as dots and its median as a bar (matplotlib,
    no display needed). A figure no task has is not drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_figures(rows)
    seqs = list(dict.fromkeys(k[0] for k in groups))
    variants = list(dict.fromkeys(k[1] for k in groups))
    written = []
    for col, fname in (("ate_m", "ate.png"), ("psnr_db", "psnr.png")):
        if not any(g[col] for g in groups.values()):
            continue
        fig, axes = plt.subplots(1, len(seqs), figsize=(max(4.0, 1.2 + 0.9 * len(variants)) * len(seqs), 3.8),
                                 squeeze=False)
        for ax, s in zip(axes[0], seqs):
            for i, v in enumerate(variants):
                xs = groups.get((s, v), {}).get(col, [])
                if not xs:
                    continue
                ax.bar(i, _median(xs), color=f"C{i % 10}", alpha=0.45, width=0.7)
                ax.plot([i] * len(xs), xs, "o", color=f"C{i % 10}", markersize=4)
            ax.set_xticks(range(len(variants)))
            ax.set_xticklabels(variants, rotation=30, ha="right")
            ax.set_title(s, fontsize=9)
            ax.set_ylabel(FIGURES[col][0])
            if col == "psnr_db":
                vals = [x for v in variants for x in groups.get((s, v), {}).get(col, [])]
                if vals:
                    ax.set_ylim(max(0.0, min(vals) - 2.0), max(vals) + 1.0)
        fig.suptitle(f"{FIGURES[col][0]}: median (bar) and each run (dots)")
        fig.tight_layout()
        path = out_dir / fname
        try:
            with atomic_path(path) as tmp:
                fig.savefig(tmp, dpi=100)
        finally:
            plt.close(fig)
        written.append(path)
    return written


def _settings(rows: list[dict]) -> dict:
    """(sequence, variant) -> the set of its runs' commands without --out and the seed (what the runs were asked to
    do)."""
    import re

    out: dict = {}
    for r in rows:
        cmd = re.sub(r" --out \S+| --set runtime\.seed=\d+", "", r.get("command") or "")
        out.setdefault((r["sequence"], r["variant"]), set()).add(cmd)
    return out


def compare_tables(a_rows: list[dict], b_rows: list[dict], a_name: str = "A", b_name: str = "B") -> tuple[list[str], int]:
    """Which headline figures moved from A to B beyond the run-to-run spread. Rule (docs/bench.md): for each
    sequence, variant and figure with finished runs on both sides, the figure **moved** when the two ranges
    [min, max] of the runs do not overlap (every run of B above every run of A, or below), i.e. the change of the
    medians is larger than the runs' own spread; with one run on a side its range is the single value. Returns the
    report's lines and the number of figures that moved."""
    ga, gb = group_figures(a_rows), group_figures(b_rows)
    ca, cb = _settings(a_rows), _settings(b_rows)
    lines = [f"A = {a_name}, B = {b_name}: a figure moved when the runs' ranges [min, max] do not overlap",
             "sequence | variant | figure | A median (min-max, runs) | B median (min-max, runs) | change | verdict"]
    moved = 0
    common = [k for k in ga if k in gb]
    for k in common:
        if ca.get(k) != cb.get(k):
            lines.append(f"{k[0]} | {k[1]}: the runs' settings differ between A and B (the command column, --out "
                         "and the seed aside)")
        for c, (label, _, better) in FIGURES.items():
            xa, xb = ga[k][c], gb[k][c]
            if not xa or not xb:
                continue
            ma, mb = _median(xa), _median(xb)
            if min(xb) > max(xa) or max(xb) < min(xa):
                up = mb > ma
                good = (up and better == "higher") or (not up and better == "lower")
                verdict = f"MOVED {'up' if up else 'down'} ({'better' if good else 'worse'})"
                moved += 1
            else:
                verdict = "within spread"
            change = f"{mb - ma:+.4g}" + (f" ({100 * (mb - ma) / abs(ma):+.1f}%)" if ma else "")
            note = " (one run a side: no spread known)" if len(xa) == 1 and len(xb) == 1 and verdict != "within spread" else ""
            lines.append(f"{k[0]} | {k[1]} | {label} | {_fmt(ma, c)} ({_fmt(min(xa), c)}-{_fmt(max(xa), c)}, "
                         f"{len(xa)}) | {_fmt(mb, c)} ({_fmt(min(xb), c)}-{_fmt(max(xb), c)}, {len(xb)}) | {change} | "
                         f"{verdict}{note}")
    only_a = [k for k in ga if k not in gb]
    only_b = [k for k in gb if k not in ga]
    for k in only_a:
        lines.append(f"{k[0]} | {k[1]}: only in {a_name}")
    for k in only_b:
        lines.append(f"{k[0]} | {k[1]}: only in {b_name}")
    lines.append(f"{moved} figure(s) moved beyond the run-to-run spread" if common else
                 "no (sequence, variant) in both tables")
    return lines, moved
