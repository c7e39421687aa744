"""``mgso run`` on a live stream (docs/live.md): an HTTP MJPEG server in this process plays the synthetic room to a
``mgso run http://127.0.0.1:PORT/stream.mjpg`` subprocess, which reads it through OpenCV's FFmpeg as it would an IP
camera. Checked: SIGTERM writes every output and exits 143 without the final refinement; the first Ctrl-C ends the
stream with it (exit 0), a second one cuts it short (130); a stream that stops sending ends the run after
``input.live_timeout_s`` with the outputs written (a bounded run ends by its limit instead: the negative control);
a stream that does not open, or one without a calibration, is one line; the live settings (real time forced, no
evaluation that reads frames back) and the limits of ``--max-frames`` / ``--duration``."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import pytest
from child_process import child_env, communicate

from mgso import synthetic
from mgso.app.cli import build_parser, main

CLI = "import sys; from mgso.app.cli import main; sys.exit(main(sys.argv[1:]))"
SMALL_MAP = ["--set", "mapping.mapper.iterations_per_keyframe=3", "--set", "mapping.mapper.final_iterations=10",
             "--set", "output.plot=false"]
OUTPUTS = ("config.yaml", "sequence.json", "frames.csv", "trajectory.txt", "keyframes.txt", "map.ply", "points.ply",
           "metrics.json")


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """40 frames of the synthetic room at 128x96 as BGR uint8, and a calibration file of its camera."""
    seq = synthetic.make_sequence(num_frames=40, width=128, height=96, seed=0)
    frames = [cv2.cvtColor(np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
              for img in seq.images]
    calib = tmp_path_factory.mktemp("live_cli") / "camera.txt"
    K = seq.K
    calib.write_text(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    return frames, calib


class MjpegServer:
    """Serves ``frames`` as a multipart JPEG stream at ``fps``: ``loop`` plays them forwards and backwards without
    end, else ``passes`` times (forwards, backwards, ...), then holds the connection open without sending (a stalled
    stream)."""

    def __init__(self, frames, fps: float, loop: bool = False, stall_s: float = 120.0, passes: int = 1):
        jpegs = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes() for f in frames]
        order = list(range(len(jpegs)))
        stop = self._stop = threading.Event()

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                t0, n = time.monotonic(), 0
                seq = order
                left = passes
                while not stop.is_set():
                    for i in seq:
                        wait = t0 + n / fps - time.monotonic()
                        if wait > 0 and stop.wait(wait):
                            return
                        b = jpegs[i]
                        try:
                            self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                             % len(b) + b + b"\r\n")
                            self.wfile.flush()
                        except OSError:
                            return
                        n += 1
                    left -= 1
                    if not loop and left <= 0:
                        stop.wait(stall_s)
                        return
                    seq = seq[::-1][1:] if not loop else seq[::-1]   # back and forth: the camera sways, no jump

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self):
        self._stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()


def _spawn(args):
    return subprocess.Popen([sys.executable, "-c", CLI, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=child_env())


def _rows(path: Path) -> int:
    return max(0, len(path.read_text().splitlines()) - 1) if path.is_file() else 0


def _finish(proc, timeout: float = 300.0):
    try:
        return communicate(proc, timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _check_outputs(out: Path, interrupted: bool = False) -> dict:
    for name in OUTPUTS:
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    fr = metrics["frames"]
    assert metrics["mode"] == "realtime"
    # every frame read was processed or dropped (frames still waiting in the player when a signal stops the run
    # count as dropped); a signal may leave the frame the odometry was on in neither
    extra = fr["read"] - fr["processed"] - fr["dropped"]
    assert (0 <= extra <= 2) if interrupted else extra == 0, fr
    assert fr["processed"] == _rows(out / "frames.csv")
    assert metrics["render"] == [] and metrics["ate"] == []          # no ground truth, nothing read back
    seq = json.loads((out / "sequence.json").read_text())
    assert seq["layout"] == "live" and seq["frames"] is None and seq["groundtruth"]["present"] is False
    assert seq["path_absolute"] == seq["path"] and "://" in seq["path"]     # a URL, not a resolved file path
    return metrics


# ------------------------------------------------------------------------------------------------ signals
@pytest.mark.slow
def test_sigterm_ends_a_live_run_with_every_output_and_exit_143(room, tmp_path):
    frames, calib = room
    server = MjpegServer(frames, fps=15.0, loop=True)
    out = tmp_path / "run"
    proc = _spawn(["run", server.url, "--calib", str(calib), "--out", str(out), "-q", *SMALL_MAP])
    try:
        deadline = time.monotonic() + 240
        while _rows(out / "frames.csv") < 15:
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"the run ended or stalled before the signal: {_finish(proc)[1][-2000:]}")
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = _finish(proc)
    finally:
        server.close()
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "mgso run: SIGTERM: stopped after" in err
    metrics = _check_outputs(out, interrupted=True)
    assert metrics["interrupted"] is True and metrics["frames"]["processed"] >= 15
    assert metrics["mapper"]["final_steps"] == 0                     # SIGTERM stops at once: no refinement
    assert metrics["live"]["end_reason"] == "stopped"
    cfg = (out / "config.yaml").read_text()
    assert "mode: realtime" in cfg and "live_timeout_s" in cfg


def _initialised(path: Path) -> bool:
    return path.is_file() and any(line.split(",")[2] == "initialized" for line in path.read_text().splitlines()[1:]
                                  if line.count(",") > 2)


def _wait_for(proc, path: Path, cond, what: str, timeout: float = 240.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if proc.poll() is not None or time.monotonic() > deadline:
            err = path.read_text() if path.is_file() else ""
            pytest.fail(f"the run ended or stalled before {what}: {err[-2000:]}")
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.parametrize("twice", [False, True])
def test_ctrl_c_ends_a_live_stream_and_a_second_one_cuts_the_refinement(room, tmp_path, twice):
    """Ctrl-C is how a live camera is ended: the first one ends the stream as its end (the odometry finishes, the map
    gets its whole final refinement, every output, exit 0). A second one, once the refinement runs, cuts it short
    (exit 130, the steps made counted). SIGTERM above is the negative control: no refinement at all."""
    frames, calib = room
    server = MjpegServer(frames, fps=15.0, loop=True)
    out = tmp_path / "run"
    final = 100000 if twice else 10        # long enough to be cut for certain; short enough to finish
    err_path = tmp_path / "stderr.txt"
    with open(err_path, "w") as err_fh:
        proc = subprocess.Popen([sys.executable, "-c", CLI, "run", server.url, "--calib", str(calib), "--out",
                                 str(out), *SMALL_MAP, "--set", f"mapping.mapper.final_iterations={final}"],
                                stdout=subprocess.PIPE, stderr=err_fh, text=True,
                                env=child_env())
        try:
            # 15 frames and the initialiser done: the map has keyframes to refine
            _wait_for(proc, err_path, lambda: _rows(out / "frames.csv") >= 15 and _initialised(out / "frames.csv"),
                      "15 frames and a keyframe")
            proc.send_signal(signal.SIGINT)
            if twice:
                _wait_for(proc, err_path, lambda: "final refinement:" in err_path.read_text(), "the refinement")
                time.sleep(1.0)
                proc.send_signal(signal.SIGINT)
            so, _ = _finish(proc)
        finally:
            server.close()
    err = err_path.read_text()
    assert "Traceback" not in err
    assert "Ctrl-C: the live stream ends here" in err
    assert "input ended by Ctrl-C" in so
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["live"]["end_reason"] == "interrupt" and metrics["live"]["captured"] == metrics["frames"]["read"]
    steps = metrics["mapper"]["final_steps"]
    if twice:
        assert proc.returncode == 130, err[-3000:]
        assert "mgso run: SIGINT: stopped after" in err
        _check_outputs(out, interrupted=True)
        assert metrics["interrupted"] is True and 0 < steps < final
    else:
        assert proc.returncode == 0, err[-3000:]
        _check_outputs(out)
        assert metrics["interrupted"] is False and steps == final
        assert metrics["frames"]["processed"] >= 15


# ------------------------------------------------------------------------------------------------ stalls
@pytest.mark.slow
@pytest.mark.parametrize("bounded", [False, True])
def test_a_stream_that_stops_sending_ends_the_run_after_the_timeout(room, tmp_path, bounded):
    """The server sends the 40 frames forwards and back (79), then nothing (the connection stays open: a network gone
    quiet). The run ends after input.live_timeout_s as at the end of the input: exit 0, every output, a warning.
    Negative control (bounded): --max-frames 60 ends it by the limit, before the stall, without the warning.

    Two passes, not one, and exit 0 only (the test used to accept exit 1, "no frame got a pose", seen once on a
    loaded machine): the stream is opened (and probed) before the mapper's process starts, and what the server sends
    meanwhile waits in the socket, to be read in a burst of which the capture keeps the newest frame; a start that
    took most of a 4 s stream would leave the initialiser too few frames, 7.9 s leave it a steady stream after any
    start. (With three busy loops beside it on the 2 cores, one pass also ended with exit 0: the failure was not
    reproduced here.) The bounded run's limit was 25 frames until CI saw that run end with exit 1 (2026-12-06: 25 read,
    19 through the tracker after the start's burst, no initialisation); 60 leave the initialiser the steady stream
    and still end 1.8 s before the stall."""
    frames, calib = room
    server = MjpegServer(frames, fps=10.0, stall_s=120.0, passes=2)
    out = tmp_path / "run"
    limit = ["--max-frames", "60"] if bounded else []
    proc = _spawn(["run", server.url, "--calib", str(calib), "--out", str(out), *SMALL_MAP,
                   "--set", "input.live_timeout_s=3", *limit])
    try:
        so, err = _finish(proc)
    finally:
        server.close()
    assert proc.returncode == 0, err[-3000:]        # a run that ended as at the end of the input
    assert "Traceback" not in err
    metrics = _check_outputs(out)
    assert metrics["interrupted"] is False
    if bounded:
        assert "no frame for" not in err and "input ended by the limit of 60 frames" in so
        assert metrics["frames"]["read"] == 60
    else:
        assert "no frame for" in err and "input.live_timeout_s" in err
        assert "input ended by no frame for 3 s" in so
        assert metrics["frames"]["read"] == 78                        # 79 sent, less the probe at open


# ------------------------------------------------------------------------------------------------ errors
def _one_line(args) -> tuple[int, list[str]]:
    proc = subprocess.run([sys.executable, "-c", CLI, *args], capture_output=True, text=True, timeout=120)
    return proc.returncode, [ln for ln in proc.stderr.splitlines() if ln.strip()]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_stream_that_does_not_open_is_one_line_and_no_output(room, tmp_path):
    url = f"rtsp://127.0.0.1:{_closed_port()}/live"
    code, err = _one_line(["run", url, "--calib", str(room[1]), "--out", str(tmp_path / "run")])
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"mgso run: error: {url}: cannot be opened")
    assert not (tmp_path / "run").exists()


def test_a_live_source_without_calibration_says_how_to_give_one(tmp_path):
    code, err = _one_line(["run", "camera:0", "--out", str(tmp_path / "run")])
    assert code == 1 and len(err) == 1, err
    assert "camera 0: a live source needs a calibration" in err[0] and "--calib FILE" in err[0]


# ------------------------------------------------------------------------------------------------ settings
def test_live_settings_force_real_time_and_warn_when_deterministic_was_asked(caplog):
    from mgso.app.cli import _live_and_limits
    from mgso.config import load_config

    parser = build_parser()
    args = parser.parse_args(["run", "camera:0", "--set", "system.mode=deterministic", "--max-frames", "50",
                              "--duration", "12.5"])
    cfg = _live_and_limits(args, load_config(None, args.set))
    assert cfg.system.mode == "realtime" and not cfg.system.eval_monogs and not cfg.system.eval_photo_slam
    assert cfg.input.live_max_frames == 50 and cfg.input.live_duration_s == 12.5
    assert any("always runs in real time" in r.getMessage() for r in caplog.records)
    caplog.clear()
    # negative control: not asked, no warning (still real time); a recorded sequence keeps its settings
    args = parser.parse_args(["run", "rtsp://cam/1"])
    assert _live_and_limits(args, load_config(None, [])).system.mode == "realtime"
    assert not any("always runs in real time" in r.getMessage() for r in caplog.records)
    args = parser.parse_args(["run", "some/folder", "--max-frames", "10", "--set", "input.stride=2"])
    cfg = _live_and_limits(args, load_config(None, args.set))
    assert cfg.system.mode == "deterministic" and cfg.system.eval_monogs and cfg.input.end == 19


@pytest.mark.parametrize("opts,msg", [(["--max-frames", "0"], "--max-frames must be >= 1"),
                                      (["--duration", "-2"], "--duration must be > 0"),
                                      (["--duration", "5"], "--duration bounds a live camera or stream")])
def test_bad_limits_are_one_line(tmp_path, capsys, opts, msg):
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "run"), *opts]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and msg in err[0], err
    assert not (tmp_path / "run").exists()


def test_max_frames_bounds_a_recorded_sequence(tmp_path):
    room = synthetic.write_tum_rgbd(tmp_path / "room", seed=0, num_frames=12, width=64, height=48)
    out = tmp_path / "run"
    assert main(["run", str(room), "--stage", "check", "--max-frames", "5", "--out", str(out), "-q"]) == 0
    assert json.loads((out / "sequence.json").read_text())["frames"] == 5
