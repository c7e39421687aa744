"""Where the real test recordings live: ``$MGSO_DATA``, else ``../shared/data`` next to the checkout."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["shared_data_dir"]


def shared_data_dir() -> Path | None:
    """The folder of real recordings, or ``None`` when it is not on this machine (a user's fresh clone)."""
    env = os.environ.get("MGSO_DATA")
    candidates = [Path(env).expanduser()] if env else []
    repo = Path(__file__).resolve().parents[2]
    candidates += [repo.parent / "shared" / "data", Path.cwd().parent / "shared" / "data",
                   repo.parent.parent / "shared" / "data"]  # a git worktree one level deeper (wt/<name>)
    for c in candidates:
        if c.is_dir():
            return c.resolve()
    return None
