"""``mgso bench`` (issue 16, docs/bench.md) on a real local Ray with 2 CPUs: two short synthetic sequences x 2
variants x 2 seeds. The table's figures are those of a direct ``mgso run`` of the same job, a second invocation skips
every task, a task that fails is recorded in its row without stopping the others, and a bad spec is one line before
any task starts. One Ray session serves the module (started by a fixture; the bench uses an initialised Ray as it is).
"""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mgso import synthetic
from mgso.app.bench_report import compare_tables, read_results_csv, summary_markdown
from mgso.app.bench_spec import SpecError, load_spec
from mgso.app.cli import main

ray = pytest.importorskip("ray", reason="mgso bench needs Ray (the test extra installs it)")

SMALL_FULL = ["mapping.mapper.iterations_per_keyframe=2", "mapping.mapper.final_iterations=5", "output.plot=false",
              "system.eval_photo_slam=false"]


def _spec_text(seqs: list[str], *, seeds=(0, 1), variants: str | None = None) -> str:
    variants = variants or ("variants:\n  odo: {}\n  full:\n    stage: full\n    set:\n"
                            + "".join(f"      - {s}\n" for s in SMALL_FULL))
    return (f"name: tiny\nstage: odometry\nseeds: [{', '.join(map(str, seeds))}]\ndata_root: data\n"
            f"sequences: [{', '.join(seqs)}]\n{variants}")


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory):
    """A folder with data/a, data/b (24 frames of the synthetic room at 96x72, two scene seeds) and spec.yaml."""
    root = tmp_path_factory.mktemp("bench")
    for name, seed in (("a", 0), ("b", 1)):
        synthetic.write_tum_rgbd(root / "data" / name, seed=seed, num_frames=24, width=96, height=72)
    (root / "spec.yaml").write_text(_spec_text(["a", "b"]))
    return root


@pytest.fixture(scope="module")
def ray_session():
    started = not ray.is_initialized()
    if started:
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    if started:
        ray.shutdown()


def test_ctrl_c_cancels_the_tasks_keeps_what_finished_and_exits_130(bench_dir, tmp_path):
    """A real `mgso bench` process with its own local Ray (before the module's Ray session starts): SIGINT while a
    long task runs. The finished task stays in the table, the running one gets SIGINT, writes what it did and is
    recorded interrupted (exit 130 of its run), and the bench exits 130 without a traceback."""
    import os
    import signal
    import time

    spec = tmp_path / "slow.yaml"
    spec.write_text(f"data_root: {bench_dir / 'data'}\nstage: full\nsequences: [a]\nvariants:\n"
                    "  quick: {stage: odometry}\n  slow:\n    set: [mapping.mapper.iterations_per_keyframe=2, "
                    "mapping.mapper.final_iterations=1000000, output.plot=false]\n")
    out = tmp_path / "out"
    # a cluster address nobody answers (a `ray start` that has ended leaves such a file behind): the default is a Ray
    # of the bench's own all the same (it failed with "When connecting to an existing cluster, num_cpus ...")
    env = dict(os.environ, PYTHONUNBUFFERED="1", RAY_ADDRESS="127.0.0.1:9")
    proc = subprocess.Popen([sys.executable, "-m", "mgso.app.cli", "bench", str(spec), "--out", str(out),
                             "--num-cpus", "2", "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120:
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            rows = read_results_csv(out / "results.csv") if (out / "results.csv").is_file() else []
            slow = [r for r in rows if r["variant"] == "slow"]
            started = slow and (Path(slow[0]["run_dir"]) / "frames.csv").is_file()
            if any(r["status"] == "ok" for r in rows) and started:
                break
            time.sleep(0.2)
        else:
            pytest.fail("the quick task did not finish in time")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err and "interrupted (SIGINT)" in err
    rows = {r["variant"]: r for r in read_results_csv(out / "results.csv")}
    assert rows["quick"]["status"] == "ok"
    assert rows["slow"]["status"] == "interrupted" and rows["slow"]["exit_code"] == "130"
    assert (Path(rows["slow"]["run_dir"]) / "trajectory.txt").is_file()      # the run wrote what it did


@pytest.fixture(scope="module")
def first_bench(bench_dir, ray_session):
    """The first invocation: every task runs."""
    out = bench_dir / "out"
    rc = main(["bench", str(bench_dir / "spec.yaml"), "--out", str(out), "-q"])
    return rc, out, read_results_csv(out / "results.csv")


def _row(rows, seq, variant, seed):
    [r] = [r for r in rows if (r["sequence"], r["variant"], r["seed"]) == (seq, variant, str(seed))]
    return r


def test_bench_runs_every_task_with_the_figures_of_a_direct_run(first_bench, bench_dir, tmp_path):
    rc, out, rows = first_bench
    assert rc == 0
    assert len(rows) == 8
    assert {(r["sequence"], r["variant"], r["seed"]) for r in rows} == {
        (s, v, str(k)) for s in "ab" for v in ("odo", "full") for k in (0, 1)}
    assert all(r["status"] == "ok" and r["exit_code"] == "0" and r["skipped"] == "False" for r in rows)
    for r in rows:    # each task wrote the run folder of an mgso run, with its record
        d = Path(r["run_dir"])
        assert d.parent == out / "runs" and d.name == r["key"]
        assert {"metrics.json", "trajectory.txt", "config.yaml", "frames.csv", "bench.json"} <= {
            p.name for p in d.iterdir()}
        assert float(r["wall_s"]) > 0 and float(r["cpu_s"]) > 0 and r["host"] and r["mgso_version"]
        assert r["ate_m"] != ""
        # the trajectory check (docs/evaluation.md) is in every row; these 24-frame runs are too short for the scale
        # drift's parts (the headline column stays empty), not for what standing still would score
        assert float(r["metrics.trajectory_check.standing_still_m"]) > 10 * float(r["ate_m"])
    assert all(_row(rows, s, "full", k)["gaussians"] not in ("", "0") for s in "ab" for k in (0, 1))
    assert len({r["key"] for r in rows}) == 8

    # a direct `mgso run` of two of the jobs (its own process, as a user would type it) gives the same figures
    spec = load_spec(bench_dir / "spec.yaml")
    for seq, variant, seed in (("b", "full", 1), ("a", "odo", 0)):
        [task] = [t for t in spec.tasks if (t.sequence, t.variant, t.seed) == (seq, variant, seed)]
        direct = tmp_path / f"{seq}-{variant}-{seed}"
        p = subprocess.run([sys.executable, "-m", "mgso.app.cli", *task.run_args(direct), "-q"], capture_output=True,
                           text=True)
        assert p.returncode == 0, p.stderr[-2000:]
        row = _row(rows, seq, variant, seed)
        direct_row = _direct_figures(direct)
        for col in ("ate_m", "scale_drift", "gaussians", "map_mb"):
            assert row[col] == direct_row[col], (col, row[col], direct_row[col])
        assert (direct / "trajectory.txt").read_bytes() == (Path(row["run_dir"]) / "trajectory.txt").read_bytes()

    # the comparison can fail: another seed of the same job gives other figures
    assert _row(rows, "b", "full", 0)["ate_m"] != _row(rows, "b", "full", 1)["ate_m"]
    assert (out / "summary.md").is_file() and (out / "ate.png").stat().st_size > 1000


def _direct_figures(run_dir: Path) -> dict:
    """The headline figures of a run folder as the bench puts them in its table."""
    import json

    from mgso.app.bench_report import _cell, flatten_metrics, headline

    return {k: _cell(v) for k, v in headline(flatten_metrics(json.loads((run_dir / "metrics.json").read_text()))).items()}


def test_a_second_invocation_skips_every_finished_task(first_bench, bench_dir):
    rc, out, rows = first_bench
    stamps = {r["key"]: (Path(r["run_dir"]) / "bench.json").stat().st_mtime_ns for r in rows}
    assert main(["bench", str(bench_dir / "spec.yaml"), "--out", str(out), "-q"]) == 0
    again = read_results_csv(out / "results.csv")
    assert len(again) == 8 and all(r["skipped"] == "True" and r["status"] == "ok" for r in again)
    assert {r["key"]: (Path(r["run_dir"]) / "bench.json").stat().st_mtime_ns for r in again} == stamps
    for a, b in zip(rows, again):        # the table is the same but for the skipped column
        assert {k: v for k, v in a.items() if k != "skipped"} == {k: v for k, v in b.items() if k != "skipped"}

    # negative control: a task recorded as failed runs again (and only that one)
    victim = _row(again, "a", "odo", 1)
    rec = Path(victim["run_dir"]) / "bench.json"
    rec.write_text(rec.read_text().replace('"status": "ok"', '"status": "failed"'))
    assert main(["bench", str(bench_dir / "spec.yaml"), "--out", str(out), "-q"]) == 0
    third = read_results_csv(out / "results.csv")
    assert [r["skipped"] for r in third].count("False") == 1
    assert _row(third, "a", "odo", 1)["skipped"] == "False" and _row(third, "a", "odo", 1)["status"] == "ok"
    assert _row(third, "a", "odo", 1)["ate_m"] == victim["ate_m"]


def test_a_failing_task_is_recorded_in_its_row_and_the_others_go_on(first_bench, bench_dir, tmp_path, capsys):
    from mgso.app.bench import run_bench

    rc, out, rows = first_bench
    shutil.copytree(bench_dir / "data" / "a", bench_dir / "data" / "gone")
    spec_path = bench_dir / "spec_gone.yaml"
    spec_path.write_text(_spec_text(["a", "gone", "b"], seeds=(0,)))
    spec = load_spec(spec_path)               # the spec check passes: the sequence is there
    shutil.rmtree(bench_dir / "data" / "gone")  # ... and vanishes before its task runs
    result = run_bench(spec, out, progress=False)
    table = read_results_csv(out / "results.csv")
    assert len(table) == 6 and result.exit_code == 1 and result.failed == 2
    gone = [r for r in table if r["sequence"] == "gone"]
    assert all(r["status"] == "failed" and r["exit_code"] == "1" and "gone" in r["error"] for r in gone)
    assert all("\n" not in r["error"] and "Traceback" not in r["error"] for r in gone)
    others = [r for r in table if r["sequence"] != "gone"]
    assert all(r["status"] == "ok" and r["skipped"] == "True" for r in others)
    summary = (out / "summary.md").read_text()
    assert "gone / odo / seed 0: failed" in summary and "a / odo / seed 0" not in summary
    # the next full spec run still has its 8 rows, all ok (the failed rows belong to the other spec)
    assert main(["bench", str(bench_dir / "spec.yaml"), "--out", str(out), "-q"]) == 0
    assert len(read_results_csv(out / "results.csv")) == 8


@pytest.mark.parametrize("body,entry", [
    ("sequences: [a, nope]\nvariants: {odo: {}}\n", "sequences[1]"),                    # unknown sequence
    ("sequences: [a]\nvariants:\n  odo:\n    set: [tracking.no_such_key=1]\n", "variants.odo.set[0]"),  # setting
    ("sequences: [a]\nvariants:\n  odo:\n    set: [tracking.huber_th=-1]\n", "variants.odo.set[0]"),   # range
    ("sequences: [a]\nvariants:\n  odo: {stage: fly}\n", "variants.odo.stage"),
    ("sequences: [a]\nvariants:\n  odo: {sett: []}\n", "variants.odo"),
    ("sequences: [a\nvariants: {odo: {}}\n", "not valid YAML"),                          # bad YAML
    ("sequence: [a]\n", "unknown key 'sequence'"),
    ("sequences: [a]\nseeds: [0, 0]\n", "seeds"),
])
def test_spec_errors_are_one_line_naming_the_file_and_entry_before_any_task(bench_dir, tmp_path, capsys, body,
                                                                            entry):
    spec = tmp_path / "spec.yaml"
    spec.write_text(f"data_root: {bench_dir / 'data'}\n" + body)
    out = tmp_path / "never"
    assert main(["bench", str(spec), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("mgso bench: error: ") and str(spec) in err and entry in err, err
    assert not out.exists()                   # nothing started
    with pytest.raises(SpecError):
        load_spec(spec)


def test_spec_error_is_one_line_from_the_command_line_too(bench_dir, tmp_path):
    """The same through ``python -m mgso.app.cli`` (whose __main__ module has a CliError class of its own)."""
    spec = tmp_path / "spec.yaml"
    spec.write_text(f"data_root: {bench_dir / 'data'}\nsequences: [a, nope]\n")
    p = subprocess.run([sys.executable, "-m", "mgso.app.cli", "bench", str(spec), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert p.returncode == 1 and p.stderr.strip().splitlines() == [
        f"mgso bench: error: {spec}: sequences[1]: 'nope': unknown sequence: no such file or folder "
        f"({bench_dir / 'data' / 'nope'})"], p.stderr
    assert not (tmp_path / "o").exists()


def test_a_good_spec_passes_the_check(bench_dir):
    """Negative control of the spec errors: the same layout with valid entries loads, as mappings and globs too."""
    spec = bench_dir / "good.yaml"
    spec.write_text("data_root: data\nrepeats: 2\nsequences:\n  - {path: a, name: first}\n  - 'b*'\nvariants:\n"
                    "  odo:\n    set: {tracking.huber_th: 9, window.max_frames: 6}\n  full: {stage: full}\n")
    s = load_spec(spec)
    assert [q.name for q in s.sequences] == ["first", "b"] and s.seeds == [0, 1] and len(s.tasks) == 8
    assert "tracking.huber_th=9" in s.tasks[0].sets and "runtime.seed=1" in s.tasks[1].sets
    assert len({t.key for t in s.tasks}) == 8


def test_a_spec_may_give_the_intrinsics_as_numbers(bench_dir, tmp_path):
    """``calib: "fx fy cx cy"`` in a sequence entry is the intrinsics themselves (as ``mgso run --calib``): the task's
    command carries them; three numbers are refused at the check, naming the entry."""
    spec = tmp_path / "num.yaml"
    spec.write_text(f"data_root: {bench_dir / 'data'}\nsequences:\n  - {{path: a, calib: '70 70 47.5 35.5'}}\n"
                    "variants: {odo: {}}\n")
    s = load_spec(spec)
    assert s.sequences[0].calib == "70 70 47.5 35.5"
    args = s.tasks[0].run_args("out")
    assert args[args.index("--calib") + 1] == "70 70 47.5 35.5"
    assert "--calib '70 70 47.5 35.5'" in s.tasks[0].command("out")
    spec.write_text(f"data_root: {bench_dir / 'data'}\nsequences:\n  - {{path: a, calib: '70 70 47.5'}}\n")
    with pytest.raises(SpecError, match=r"sequences\[0\].*expected 4 \(fx fy cx cy\)"):
        load_spec(spec)


def test_compare_says_what_moved_beyond_the_spread(first_bench, tmp_path, capsys):
    def rows(values: dict) -> list[dict]:
        return [{"sequence": "s", "variant": v, "seed": str(i), "status": "ok", "ate_m": str(x)}
                for v, xs in values.items() for i, x in enumerate(xs)]

    a = rows({"v": [1.0, 1.1, 1.2], "w": [2.0, 2.1]})
    lines, moved = compare_tables(a, rows({"v": [1.15, 1.3, 1.25], "w": [2.5, 2.6]}))
    assert moved == 1
    [v_line] = [ln for ln in lines if ln.startswith("s | v |")]
    [w_line] = [ln for ln in lines if ln.startswith("s | w |")]
    assert "within spread" in v_line and "MOVED up (worse)" in w_line     # a higher ATE is worse
    assert compare_tables(a, a)[1] == 0                                    # negative control
    assert not any("settings differ" in ln for ln in lines)
    b = [dict(r, command=f"mgso run s --out /x/{i} --set runtime.seed={r['seed']}" + (" --set a.b=1" if r["variant"]
                                                                                     == "w" else ""))
         for i, r in enumerate(a)]
    flagged = [ln for ln in compare_tables([dict(r, command=f"mgso run s --out /y --set runtime.seed={r['seed']}")
                                            for r in a], b)[0] if "settings differ" in ln]
    assert [ln.split(" | ")[1].split(":")[0] for ln in flagged] == ["w"]    # the seed and --out do not count

    # the command on two results.csv: the bench against itself moved nothing
    _, out, _ = first_bench
    csv_a = out / "results.csv"
    assert main(["bench", "--compare", str(csv_a), str(csv_a)]) == 0
    assert "0 figure(s) moved" in capsys.readouterr().out
    assert main(["bench", "--compare", str(csv_a), str(tmp_path / "missing.csv")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "missing.csv" in err


def test_summary_marks_the_winner_of_each_column():
    rows = [{"sequence": "s", "variant": v, "seed": str(i), "status": "ok", "ate_m": str(x), "psnr_db": str(p)}
            for v, xs, ps in (("v", [0.2, 0.3, 0.25], [20, 21, 22]), ("w", [0.1, 0.5, 0.12], [19, 20, 20.5]))
            for i, (x, p) in enumerate(zip(xs, ps))]
    rows.append({"sequence": "s", "variant": "w", "seed": "3", "status": "failed", "error": "boom", "ate_m": ""})
    text = summary_markdown(rows, "t")
    [v] = [ln for ln in text.splitlines() if ln.startswith("| s | v |")]
    [w] = [ln for ln in text.splitlines() if ln.startswith("| s | w |")]
    assert "0.2500 (0.2000-0.3000)" in v and "**0.1200** (0.1000-0.5000)" in w     # the lower median ATE wins
    assert "**21.00** (20.00-22.00)" in v and "**" not in w.split("|")[5]           # the higher PSNR wins
    assert "3/4 (1 not ok)" in w and "s / w / seed 3: failed: boom" in text


def test_results_csv_has_every_metrics_figure(first_bench):
    _, out, rows = first_bench
    with open(out / "results.csv", newline="") as fh:
        header = next(csv.reader(fh))
    assert header[:3] == ["sequence", "variant", "seed"]
    for col in ("metrics.num_gaussians", "metrics.tracking.points", "metrics.ate_all_frames_m",
                "metrics.peak_memory_mb", "metrics.frames.processed", "commit", "ray_version", "command"):
        assert col in header, col
    full = _row(rows, "a", "full", 0)
    assert full["metrics.num_gaussians"] == full["gaussians"] and full["command"].startswith("mgso run ")


def test_the_reference_dso_row(bench_dir, tmp_path):
    """``reference_dso``: a row per sequence and seed that runs profiles/dso_reference.py with the binary (a stand-in
    here: a script that exits with the code given, writing no result.txt); its figures go into the row, a crash of
    the binary fails the row. A binary that is not executable is a spec error (one line)."""
    from mgso.app.bench import run_task

    fake = tmp_path / "dso_dataset"
    spec = tmp_path / "spec.yaml"
    cpu_ms = {}
    for code, status in ((0, "ok"), (3, "failed")):
        # the run that succeeds also spends CPU (a shell loop, ~0.3 s), so the row's process CPU must see the child's
        busy = "i=0; while [ $i -lt 100000 ]; do i=$((i+1)); done\n" if code == 0 else ""
        fake.write_text(f"#!/bin/sh\n{busy}exit {code}\n")
        fake.chmod(0o755)
        spec.write_text(f"data_root: {bench_dir / 'data'}\nstage: odometry\nseeds: [0, 1]\nsequences: [a, b]\n"
                        f"variants: {{odo: {{}}}}\nreference_dso: {{binary: {fake}}}\n")
        s = load_spec(spec)
        assert [(t.sequence, t.variant) for t in s.tasks].count(("a", "dso-reference")) == 2 and len(s.tasks) == 8
        [t] = [t for t in s.tasks if (t.sequence, t.variant, t.seed) == ("a", "dso-reference", 0)]
        rec = run_task(t.as_dict(), str(tmp_path / f"run{code}"))
        assert rec["status"] == status, rec
        assert rec["metrics"]["dso"]["frames"] == 24 and rec["metrics"]["dso"]["returncode"] == code
        cpu_ms[code] = rec["metrics"]["dso"]["process_cpu_ms_per_frame"] * 24
        if code:
            assert rec["error"] == "dso_dataset exited with 3"
    # the DSO process's CPU time (getrusage of the children): the busy run's loop counted, the bare exit's nearly not
    assert cpu_ms[0] > 50 and cpu_ms[3] < 0.5 * cpu_ms[0], cpu_ms
    fake.chmod(0o644)
    with pytest.raises(SpecError, match=r"reference_dso\.binary: .*not an executable file"):
        load_spec(spec)


def test_one_bench_at_a_time_in_a_folder(tmp_path):
    """A second bench in the same folder would empty the run folders of the first one's running tasks: refused in one
    line; once the first is done the folder is free again (negative control)."""
    from mgso.app.bench import _bench_lock
    from mgso.app.writer import OutputError

    with _bench_lock(tmp_path):
        with pytest.raises(OutputError, match="another mgso bench is running in this folder"):
            with _bench_lock(tmp_path):
                pass
    with _bench_lock(tmp_path):
        pass


@pytest.mark.parametrize("args, code, msg", [
    ([], 2, "give a SPEC"),
    (["system", "--compare", "a.csv", "b.csv"], 2, "not both"),
    (["system", "--num-cpus", "0"], 2, "--num-cpus must be >= 1, got 0"),
    (["system", "--num-cpus", "-3"], 2, "--num-cpus must be >= 1, got -3"),
    (["{tmp}"], 1, "is a folder, not a spec file"),
    (["system", "--address", "127.0.0.1:{closed}"], 1, "no Ray cluster answers there"),
    (["system", "--address", "http://127.0.0.1:1"], 1, "expected auto, HOST:PORT or ray://HOST:PORT"),
])
def test_bench_argument_mistakes_are_refused_before_any_work(tmp_path, capsys, args, code, msg):
    """Issue 44: argument mistakes exited 1 instead of the usage code 2; --num-cpus 0 meant all; a folder was "no
    such spec file"; an address with nothing listening waited forever while Ray retried. Nothing is made."""
    import socket

    with socket.socket() as s:          # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        closed = s.getsockname()[1]
    out = tmp_path / "out"
    args = [a.format(tmp=tmp_path, closed=closed) for a in args]
    assert main(["bench", *args, "--out", str(out), "-q"]) == code
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err and not out.exists()


def test_ray_client_address_without_the_client_is_one_line(tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "grpc" else real(name, *a))
    out = tmp_path / "out"
    assert main(["bench", "system", "--address", "ray://127.0.0.1:10001", "--out", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert 'pip install "ray[client]' in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_compare_refuses_an_empty_or_header_only_table(tmp_path, capsys):
    header = tmp_path / "header.csv"
    header.write_text("sequence,variant,status\n")
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    good = tmp_path / "good.csv"
    good.write_text("sequence,variant,status,seed,ate_m\ns,v,ok,0,0.1\n")
    for bad in (header, empty):
        assert main(["bench", "--compare", str(good), str(bad)]) == 1
        err = capsys.readouterr().err
        assert f"{bad}: no rows" in err and len(err.strip().splitlines()) == 1
    assert main(["bench", "--compare", str(good), str(good)]) == 0           # the control
