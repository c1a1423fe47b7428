"""What a report needs to be cited and repeated: software version, git commit, command lines, date, machine."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

import facerec3d


def git_commit() -> dict:
    """{"git_commit", "git_dirty"} of the working tree facerec3d is imported from, when it is one (an editable
    install); {} otherwise. Read-only: git is asked not to take optional locks."""
    root = Path(facerec3d.__file__).resolve().parent.parent
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}

    def git(*args: str) -> str | None:
        try:
            r = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, env=env)
        except (OSError, subprocess.SubprocessError):
            return None
        return r.stdout.strip() if r.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    commit = git("rev-parse", "HEAD")
    if not top or not commit or Path(top).resolve() != root:
        return {}
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"git_commit": commit, "git_dirty": bool(status) if status is not None else None}


def provenance(rerun: Sequence[str]) -> dict:
    """The provenance entry of metrics.json: facerec3d's version and git commit (where available), the command
    line this process was started with, ``rerun`` (an argv that repeats the run from the settings saved with
    it), the date (UTC, ISO 8601) and the machine (cores, platform, Python, NumPy)."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        usable = os.cpu_count()
    return {
        "facerec3d_version": facerec3d.__version__,
        **git_commit(),
        "command": list(sys.argv),
        "rerun": [str(a) for a in rerun],
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cores": os.cpu_count(), "usable_cores": usable, "cpu": platform.processor() or platform.machine(),
                    "platform": platform.platform(), "python": platform.python_version(), "numpy": np.__version__},
    }
