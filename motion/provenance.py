"""Where and from what a measurement was made: :func:`provenance`.

Recorded beside every generated number -- an experiment's run record
(``experiments/runner.py`` writes it as ``provenance.json``) and the benchmarks page
(``benchmarks/report.py``) -- so that a figure and the code and machine that made it travel
together.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path

import torch

__all__ = ["provenance"]


def provenance(repo: Path | None = None) -> dict:
    """Where and from what a run ran: ``commit`` (``git rev-parse HEAD`` of ``repo``,
    default this package's checkout; ``"unknown"`` outside git), ``dirty`` (uncommitted
    changes to tracked files), ``date`` (UTC, ISO 8601), ``machine`` (host name, CPU
    architecture), ``cpus`` (``os.cpu_count()``), ``threads`` (torch's intra-op threads),
    ``python`` and ``torch`` versions."""
    repo = repo or Path(__file__).resolve().parent.parent

    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(
                ["git", *args], cwd=repo, capture_output=True, text=True, timeout=10, check=True
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout.strip()

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no")
    return {
        "commit": commit or "unknown",
        "dirty": bool(status) if status is not None else None,
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.node()} ({platform.machine()})",
        "cpus": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
