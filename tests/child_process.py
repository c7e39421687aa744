"""For the tests that run mgso in a child process and stop it with a signal: a child that has not ended in time
fails its test with where each of its threads was (Python's faulthandler dumps them on SIGABRT), not with a bare
timeout. An intermittent hang in CI then says where it hung (2026-12-07: a SIGTERM'd run that never ended)."""

from __future__ import annotations

import os
import signal
import subprocess

import pytest


def child_env(**extra: str) -> dict:
    """The environment of such a child: unbuffered output, and faulthandler on (its SIGABRT dump)."""
    return dict(os.environ, PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1", **extra)


def communicate(proc: subprocess.Popen, timeout: float, what: str = "the run") -> tuple[str, str]:
    """``proc.communicate(timeout=timeout)``; past it, the child (started with :func:`child_env`) is sent SIGABRT and
    the test fails with the end of its stderr: the threads' stacks."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        pytest.fail(f"{what} had not ended after {timeout:.0f} s; its threads then:\n{(err or '')[-8000:]}")
