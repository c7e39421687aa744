"""``mgso bench SPEC``: many sequences, variants and seeds at once, each (sequence, variant, seed) one Ray task
(docs/bench.md).

- The spec is read and checked whole first (:mod:`mgso.app.bench_spec`): any problem is one line, before Ray starts.
- Each task is one ``mgso run`` (the same command line, in a child process of a Ray worker that declared the task's
  ``num_cpus`` and, when asked and the cluster has one, ``num_gpus``) writing its run folder
  ``DIR/runs/<key>/``, ``key`` the hash of the task's inputs (sequence, stage, the whole resolved configuration).
  Beside the run's own files the folder holds ``bench.json`` (how the task ended, wall and CPU time, host, versions,
  commit) and ``bench.log`` (the run's stdout and stderr).
- Resumable: a task whose ``bench.json`` says ``ok`` is skipped; any other folder (failed, interrupted, killed) is
  emptied and run again.
- The results stream back as tasks finish: ``results.csv`` is rewritten (atomically) after each, ``summary.md`` and the
  plots at the end (:mod:`mgso.app.bench_report`). A task that fails is recorded in its row; the others go on.
- Ray: a local one started here (``ray.init(num_cpus=..., include_dashboard=False)``) by default, or ``--address
  auto|ray://...`` to join a running cluster; an already initialised Ray (a test's) is used as it is.
- Ctrl-C cancels the running tasks (each run gets SIGINT, writes what it did and is recorded ``interrupted``), keeps
  what finished in the table and exits 130.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import resource
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from .bench_report import (atomic_write_text, flatten_metrics, headline, summary_markdown, write_plots,
                           write_results_csv)
from .bench_spec import DSO_STAGE, BenchSpec, Task

__all__ = ["BenchResult", "run_bench", "run_task", "task_record"]

log = logging.getLogger(__name__)

#: How long a cancelled run gets to write what it did after its SIGINT before it is killed.
CANCEL_GRACE_S = 30.0


# ------------------------------------------------------------------------------------------------ the task
def _versions() -> dict:
    from importlib import metadata

    def ver(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return ""

    from mgso import __version__

    return {"mgso_version": __version__, "python": platform.python_version(), "ray_version": ver("ray"),
            "warp_version": ver("warp-lang"), "numpy_version": ver("numpy")}


def _commit() -> str:
    """The git commit of the mgso that runs (``-dirty`` with uncommitted changes), or '' outside a checkout."""
    src = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10)
        if head.returncode != 0:
            return ""
        dirty = subprocess.run(["git", "-C", str(src), "status", "--porcelain", "-uno", "--", "mgso",
                                "mgso_kernels"], capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return ""


def _error_line(log_text: str, rc: int) -> str:
    """The run's one-line error from its stderr (``mgso run: error: ...``), else its last line."""
    lines = [ln.strip() for ln in log_text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if ln.startswith("mgso run: "):
            return ln.removeprefix("mgso run: ").removeprefix("error: ")
    return lines[-1] if lines else f"exit code {rc}"


def _stop_with_parent() -> None:
    """In the run's child process, before it starts: the stop signals as a plain process has them (a Ray worker
    blocks or ignores some, and a child inherits both: its run would not hear the SIGINT of a cancel), and (Linux)
    SIGTERM when the worker that started it dies (a task cancelled by force, a node going away), so that the run
    writes what it did and ends instead of living on."""
    stops = [signal.SIGINT, signal.SIGTERM] + ([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])
    for s in stops:
        signal.signal(s, signal.SIG_DFL)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, stops)
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run_task(task: dict, run_dir: str) -> dict:
    """Run one task (a :meth:`Task.as_dict`) as ``mgso run`` in a child process writing ``run_dir``; returns its
    record (also written as ``run_dir/bench.json``). Runs inside a Ray worker, or anywhere. A KeyboardInterrupt (how
    Ray cancels a running task) sends the run SIGINT, waits for it to write what it did, records it interrupted and
    is raised again."""
    out = Path(run_dir)
    if out.exists():                    # a failed or killed attempt: start clean
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t = Task(**{k: (tuple(v) if k == "sets" else v) for k, v in task.items()})
    rec = {"status": "running", "host": socket.gethostname(), "commit": _commit(), **_versions(),
           "command": t.command(out), "started": time.time()}
    atomic_write_text(out / "bench.json", json.dumps(rec, indent=1))
    dso = t.stage == DSO_STAGE
    cmd = [sys.executable, *t.dso_args()] if dso else [sys.executable, "-m", "mgso.app.cli", *t.run_args(out), "-q"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    interrupted = False
    with open(out / "bench.log", "w", encoding="utf-8") as logf, \
            open(out / ("dso.json" if dso else "bench.stdout"), "w", encoding="utf-8") as outf:
        # its own session: a Ctrl-C at the terminal reaches the bench, which cancels the tasks; not every run directly
        proc = subprocess.Popen(cmd, stdout=outf if dso else logf, stderr=subprocess.STDOUT if not dso else logf,
                                env=env, start_new_session=True,
                                preexec_fn=_stop_with_parent)
        try:
            while True:     # short waits: Ray's cancel arrives between bytecodes, never inside one long waitpid
                try:
                    rc = proc.wait(timeout=0.25)
                    break
                except subprocess.TimeoutExpired:
                    continue
        except KeyboardInterrupt:
            interrupted = True
            proc.send_signal(signal.SIGINT)
            try:
                rc = proc.wait(timeout=CANCEL_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                rc = proc.wait()
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    text = (out / "bench.log").read_text(encoding="utf-8", errors="replace")
    status = "ok" if rc == 0 else ("interrupted" if interrupted or rc >= 128 else "failed")
    rec.update(status=status, exit_code=rc, error=None if rc == 0 else _error_line(text, rc), wall_s=wall,
               cpu_s=(ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime), finished=time.time())
    if dso and rc == 0:
        rec["metrics"] = _dso_metrics(out, t)
        if rec["metrics"] is None:
            rec.update(status="failed", error="the reference DSO printed no result (see bench.log)")
        elif rec["metrics"]["dso"].get("returncode") != 0:
            rec.update(status="failed", exit_code=rec["metrics"]["dso"].get("returncode"),
                       error=f"dso_dataset exited with {rec['metrics']['dso'].get('returncode')}")
    try:
        if not dso:
            rec["metrics"] = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        rec["metrics"] = None
    atomic_write_text(out / "bench.json", json.dumps(rec, indent=1, default=str))
    if interrupted:
        raise KeyboardInterrupt
    return rec


def _dso_metrics(out: Path, t: Task) -> dict | None:
    """The reference DSO's figures (profiles/dso_reference.py's JSON line) as this row's metrics, also written as
    ``metrics.json``: its wall time, DSO's own CPU ms a frame and the ATE of the keyframes DSO marginalised
    (``dso.ate_marginalized_keyframes_m``: not the all-frames ATE of mgso's rows); ``dso.fps`` is frames / wall."""
    try:
        lines = [ln for ln in (out / "dso.json").read_text(encoding="utf-8").splitlines() if ln.startswith("{")]
        res = json.loads(lines[-1])
    except (OSError, ValueError, IndexError):
        return None
    one = res.get(Path(t.path).name)
    if not isinstance(one, dict):
        return None
    if one.get("wall_s"):
        one["fps"] = one.get("frames", 0) / one["wall_s"]
    metrics = {"dso": one, "load_avg_1min": res.get("load_avg_1min"), "load_avg_1min_end": res.get("load_avg_1min_end")}
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=1))
    return metrics


def task_record(run_dir: Path) -> dict | None:
    """The record of a task's earlier attempt (``bench.json``), or ``None``."""
    try:
        return json.loads((run_dir / "bench.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _row(task: Task, run_dir: Path, rec: dict | None, *, skipped: bool = False, status: str | None = None,
         error: str | None = None) -> dict:
    rec = rec or {}
    flat = flatten_metrics(rec.get("metrics"))
    row = {"sequence": task.sequence, "variant": task.variant, "seed": task.seed, "stage": task.stage,
           "status": status or rec.get("status", "not run"), "exit_code": rec.get("exit_code"),
           "error": error if error is not None else rec.get("error"), "skipped": skipped, "run_dir": str(run_dir),
           "key": task.key, "wall_s": rec.get("wall_s"), "cpu_s": rec.get("cpu_s"), "host": rec.get("host"),
           "commit": rec.get("commit"), "num_cpus": task.num_cpus, "num_gpus": task.num_gpus,
           "command": rec.get("command") or task.command(run_dir)}
    for k in ("mgso_version", "python", "ray_version", "warp_version", "numpy_version"):
        row[k] = rec.get(k)
    row.update(headline(flat))
    row.update({f"metrics.{k}": v for k, v in flat.items()})
    return row


# ------------------------------------------------------------------------------------------------ the bench
@dataclass
class BenchResult:
    out: Path
    rows: list[dict]
    ran: int = 0
    skipped: int = 0
    failed: int = 0
    interrupted: bool = False
    signum: int = signal.SIGINT
    written: list[Path] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum) if self.interrupted else (1 if self.failed else 0)

    def lines(self) -> list[str]:
        done = sum(r["status"] == "ok" for r in self.rows)
        out = [f"{len(self.rows)} tasks: {done} ok ({self.skipped} skipped: finished before), {self.failed} failed"
               + (", INTERRUPTED (the unfinished tasks run again next time)" if self.interrupted else "")]
        out += [f"wrote {p}" for p in self.written]
        return out


def _init_ray(address: str | None, num_cpus: int | None):
    """Ray: the one already initialised (a test's, a notebook's), a cluster at ``address``, or a local one started
    here. Returns the ``ray`` module and whether it was started here (then it is shut down at the end)."""
    import ray
    if ray.is_initialized():
        return ray, False
    # quiet: no dashboard, no worker logs on this terminal (each run's log is its bench.log), only Ray's errors (its
    # warnings about a local single-user cluster, such as token authentication, are not the user's concern here)
    quiet = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR,
                 configure_logging=True)
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    if address:
        ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    else:
        # the workers import mgso from where this process does (an editable checkout, a test's tree)
        src = str(Path(__file__).resolve().parents[2])
        pp = os.environ.get("PYTHONPATH", "")
        env = {"env_vars": {"PYTHONPATH": src + (os.pathsep + pp if pp else "")}}
        # address "local": a new Ray of our own even when a cluster was started on this machine (`ray start`,
        # which ray.init() would otherwise join, with num_cpus refused), or one that left its address file behind
        ray.init(address="local", num_cpus=num_cpus or os.cpu_count() or 1, runtime_env=env, **quiet)
    return ray, True


def check_address(address: str | None, timeout_s: float = 5.0) -> None:
    """Refuse, in one line and before any work, a Ray address that cannot be joined: ``ray://`` without Ray's
    client (``ray[client]``), or a ``HOST:PORT`` where nothing listens (Ray itself retries for minutes)."""
    import importlib.util

    from .bench_spec import SpecError

    if not address or address in ("auto", "local"):
        return
    hostport = address
    if address.startswith("ray://"):
        if importlib.util.find_spec("grpc") is None:
            raise SpecError(f"--address {address}: joining a cluster through ray:// needs Ray's client: "
                            'pip install "ray[client]>=2.9,<3" (or run mgso bench on the head node with '
                            "--address auto)")
        hostport = address[len("ray://"):].split("/", 1)[0]
    elif "://" in address:
        raise SpecError(f"--address {address}: expected auto, HOST:PORT or ray://HOST:PORT")
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise SpecError(f"--address {address}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise SpecError(f"--address {address}: no Ray cluster answers there ({exc.strerror or exc}); start one "
                        "with `ray start --head` or give its address") from None


def run_bench(spec: BenchSpec, out_dir: str | os.PathLike, *, address: str | None = None,
              num_cpus: int | None = None, progress: bool = True) -> BenchResult:
    """Run every task of ``spec`` not finished before into ``out_dir`` (see the module doc)."""
    from .writer import prepare_out_dir

    out = prepare_out_dir(out_dir)
    with _bench_lock(out):
        return _run_bench(spec, out, address=address, num_cpus=num_cpus, progress=progress)


@contextmanager
def _bench_lock(out: Path):
    """One bench at a time in a folder: a second would empty the run folders of the first one's running tasks."""
    import fcntl

    from .writer import OutputError

    fh = open(out / ".bench.lock", "w")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise OutputError(f"{out}: another mgso bench is running in this folder (wait for it, or give another "
                              "--out)") from None
        yield
    finally:
        fh.close()


def _run_bench(spec: BenchSpec, out: Path, *, address, num_cpus, progress: bool) -> BenchResult:
    runs = out / "runs"
    runs.mkdir(exist_ok=True)
    atomic_write_text(out / "spec.yaml", spec.text)
    rows: dict[int, dict] = {}
    todo: list[int] = []
    for i, t in enumerate(spec.tasks):
        rd = runs / t.key
        rec = task_record(rd)
        if rec is not None and rec.get("status") == "ok":
            rows[i] = _row(t, rd, rec, skipped=True)
        else:
            rows[i] = _row(t, rd, None, status="pending")
            todo.append(i)
    result = BenchResult(out=out, rows=[], skipped=len(spec.tasks) - len(todo))

    def flush() -> None:
        result.rows = [rows[i] for i in range(len(spec.tasks))]
        write_results_csv(out / "results.csv", result.rows)

    flush()
    if todo:
        _run_remote(spec, todo, runs, rows, result, flush, address=address, num_cpus=num_cpus, progress=progress)
    flush()
    result.failed = sum(r["status"] not in ("ok", "pending", "cancelled", "interrupted") for r in result.rows)
    atomic_write_text(out / "summary.md", summary_markdown(result.rows, spec.name))
    result.written = [out / "results.csv", out / "summary.md"]
    try:
        result.written += write_plots(result.rows, out)
    except Exception as exc:  # noqa: BLE001 - a figure must not lose the table
        log.warning("no plots: %s: %s", type(exc).__name__, exc)
    return result


def _run_remote(spec: BenchSpec, todo: list[int], runs: Path, rows: dict, result: BenchResult, flush, *,
                address, num_cpus, progress: bool) -> None:
    from tqdm import tqdm

    ray, started = _init_ray(address, num_cpus)
    try:
        gpus_present = ray.cluster_resources().get("GPU", 0) > 0
        cpus = ray.cluster_resources().get("CPU", 1)
        # a fresh worker process for each task (max_calls=1): nothing of one run (Warp's state, the peak memory
        # that metrics.json reports for the process) carries into the next
        remote = ray.remote(max_calls=1, max_retries=0)(run_task)
        refs = {}
        warned = False
        for i in todo:
            t = spec.tasks[i]
            gpus = t.num_gpus if gpus_present else 0
            if t.num_gpus and not gpus_present and not warned:
                log.warning("a variant asks for a GPU but the Ray cluster has none: its tasks run on the CPU")
                warned = True
            if t.num_cpus > cpus:
                rows[i].update(status="failed", error=f"the task asks for {t.num_cpus:g} CPUs, the Ray cluster has "
                                                      f"{cpus:g}")
                continue
            ref = remote.options(num_cpus=t.num_cpus, num_gpus=gpus,
                                 name=f"mgso-{t.sequence}-{t.variant}-{t.seed}").remote(t.as_dict(),
                                                                                         str(runs / t.key))
            refs[ref] = i
        slots = max(1, int(cpus // max(min(spec.tasks[i].num_cpus for i in todo), 1e-9)))
        n_done = n_failed = 0
        bar = tqdm(total=len(spec.tasks), initial=result.skipped, desc="bench", unit="task", disable=not progress,
                   dynamic_ncols=True, file=sys.stderr)

        def show() -> None:
            bar.set_postfix_str(f"done {n_done + result.skipped}, running {min(len(refs), slots)}, failed {n_failed}",
                                refresh=True)

        show()
        try:
            while refs:
                ready, _ = ray.wait(list(refs), num_returns=1, timeout=1.0)
                for ref in ready:
                    i = refs.pop(ref)
                    t = spec.tasks[i]
                    rd = runs / t.key
                    try:
                        rec = ray.get(ref)
                        rows[i] = _row(t, rd, rec)
                    except Exception as exc:  # noqa: BLE001 - the task raised or its worker died: in its row
                        rows[i] = _row(t, rd, task_record(rd), status="failed",
                                       error=f"{type(exc).__name__}: {_first_line(exc)}")
                    result.ran += 1
                    if rows[i]["status"] == "ok":
                        n_done += 1
                    else:
                        n_failed += 1
                        bar.write(f"failed: {t.sequence} / {t.variant} / seed {t.seed}: {rows[i]['error']}")
                    bar.update(1)
                    flush()
                show()
        except KeyboardInterrupt as exc:
            result.interrupted = True
            result.signum = getattr(exc, "signum", signal.SIGINT)
            bar.write("interrupted: cancelling the running tasks (each writes what it did) ...")
            for ref in refs:
                ray.cancel(ref, force=False)
            deadline = time.monotonic() + CANCEL_GRACE_S + 5
            while refs and time.monotonic() < deadline:
                ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=1.0)
                if not ready:
                    continue
                for ref in ready:
                    i = refs.pop(ref)
                    t = spec.tasks[i]
                    rd = runs / t.key
                    try:
                        rows[i] = _row(t, rd, ray.get(ref))      # finished before the cancel reached it
                    except Exception:  # noqa: BLE001 - cancelled: what it wrote says so
                        rec = task_record(rd)
                        rows[i] = _row(t, rd, rec, status="interrupted" if rec else "cancelled",
                                       error="cancelled by Ctrl-C")
            for ref, i in refs.items():
                ray.cancel(ref, force=True)
                rows[i] = _row(spec.tasks[i], runs / spec.tasks[i].key, None, status="cancelled",
                               error="cancelled by Ctrl-C")
            flush()
        finally:
            bar.close()
    finally:
        if started:
            ray.shutdown()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    # a RayTaskError's text starts with the task's name; the cause is on its last line
    return (text[-1] if text else type(exc).__name__)[:300]


# ------------------------------------------------------------------------------------------------ the command
def cmd_bench(args) -> int:
    """``mgso bench SPEC [--out DIR] [--address auto|ray://...] [--num-cpus N]`` and ``mgso bench --compare A B``."""
    from .bench_report import compare_tables, read_results_csv
    from .bench_spec import SpecError, load_spec
    from .stages import EXIT_USAGE

    CliError = SpecError    # one line on stderr, exit 1 (a ConfigError: caught by the CLI however it was started)

    def usage(msg: str) -> int:     # a mistake in the arguments: argparse's form and exit code (2)
        print(f"usage: mgso bench [SPEC] [--out DIR] [--address ADDR] [--num-cpus N] [--compare A.csv B.csv]\n"
              f"mgso bench: error: {msg}", file=sys.stderr)
        return EXIT_USAGE

    if args.num_cpus is not None and args.num_cpus < 1:
        return usage(f"--num-cpus must be >= 1, got {args.num_cpus} (leave it out for all of this machine's)")
    if args.compare:
        if args.spec:
            return usage("give a SPEC or --compare A.csv B.csv, not both")
        a, b = args.compare
        try:
            lines, _ = compare_tables(read_results_csv(a), read_results_csv(b), a, b)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        print("\n".join(lines))
        return 0
    if not args.spec:
        return usage("give a SPEC (a YAML file or a built-in name) or --compare A.csv B.csv")
    spec = load_spec(args.spec)
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        raise CliError('mgso bench needs Ray: pip install "mgso[bench]" (or pip install "ray>=2.9,<3")')
    check_address(args.address)         # before the output folder is made
    out = Path(args.out or Path("bench") / spec.name)
    if not args.quiet:
        print(f"mgso bench {spec.name}: {len(spec.sequences)} sequences x {len(spec.variants)} variants x "
              f"{len(spec.seeds)} seeds = {len(spec.tasks)} tasks -> {out}")
    result = run_bench(spec, out, address=args.address, num_cpus=args.num_cpus, progress=not args.quiet)
    if not args.quiet:
        for line in result.lines():
            print(line)
    if result.interrupted:
        name = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}.get(result.signum, str(result.signum))
        print(f"mgso bench: interrupted ({name}): the finished tasks are in the table; run the same command to "
              "finish the rest", file=sys.stderr)
    elif result.failed:
        print(f"mgso bench: {result.failed} task(s) failed: their errors are in {out / 'results.csv'} and "
              f"{out / 'summary.md'}", file=sys.stderr)
    return result.exit_code


def add_parser(sub) -> None:
    """Register ``mgso bench`` on the CLI's subparsers."""
    p = sub.add_parser("bench", help="run a benchmark spec (sequences x variants x seeds) on Ray; or compare two "
                                     "results.csv (docs/bench.md)")
    p.add_argument("spec", nargs="?", metavar="SPEC",
                   help="benchmark spec: a YAML file or a built-in name (mgso/configs/bench/: odometry, system, ...)")
    p.add_argument("--out", help="output folder (default bench/<spec name>): runs/, results.csv, summary.md, plots")
    p.add_argument("--address", help="join a running Ray cluster: 'auto' (the one started on this machine by "
                                     "`ray start`) or ray://HOST:10001; default: a local Ray started for this command")
    p.add_argument("--num-cpus", type=int, help="CPUs of the local Ray (default: all of this machine's)")
    p.add_argument("--compare", nargs=2, metavar=("A.csv", "B.csv"),
                   help="say which figures moved from A to B beyond the run-to-run spread")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, only warnings and errors")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v: debug)")
    p.set_defaults(func=cmd_bench)
