"""A test-only experiment that runs in milliseconds and can fail on demand: ``mode=raise``
raises in the run, ``mode=kill`` kills the process it runs in (only ever on a Ray worker),
``mode=interrupt`` raises ``KeyboardInterrupt`` (Ctrl-C in the middle of a sweep).

Register it for one test with :func:`register` (``monkeypatch``: the registry is restored
after the test). The module is importable by Ray workers (it is not a test file), so the
tasks that name its functions unpickle there.
"""

from __future__ import annotations

import os
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from experiments.config import ExperimentConfig
from experiments.runner import EXPERIMENTS, Experiment
from motion.settings import setting

NAME = "toy"
TIMINGS = ("sec_per_run",)
#: how many times run() was called in this process, by value of ``value``
CALLS: dict[float, int] = {}


@dataclass
class ToyConfig(ExperimentConfig):
    value: float = setting(1.0, "a number the metrics are made from")
    mode: str = setting(
        "ok", "ok, raise, kill or interrupt", choices=("ok", "raise", "kill", "interrupt")
    )
    device: str = setting(
        "cpu", "cpu or cuda (asks a Ray cluster for a GPU)", choices=("cpu", "cuda")
    )
    seed: int = setting(0, "seed", ge=0)
    out_dir: str = setting("runs/toy", "output folder")
    tiny: bool = setting(False, "no effect")

    def gpus(self) -> int:
        return int(self.device == "cuda")


def run(cfg: ToyConfig):
    CALLS[cfg.value] = CALLS.get(cfg.value, 0) + 1
    if cfg.mode == "raise":
        raise ValueError(f"value={cfg.value}: the toy run was told to fail")
    if cfg.mode == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if cfg.mode == "interrupt":
        raise KeyboardInterrupt
    g = torch.Generator().manual_seed(cfg.seed)
    noise = torch.rand(3, generator=g, dtype=torch.float64).numpy()
    metrics = {
        "score": float(cfg.value * 2 + noise.sum()),
        "threads": torch.get_num_threads(),
        "sec_per_run": 0.001,
    }
    columns = {"frame": np.arange(3), "noise": noise}
    return metrics, columns, {"noise": noise}


def plot(path, data, title: str) -> None:
    Path(path).write_bytes(f"{title}: {data['noise'].tolist()}\n".encode())
    Path(path).with_name("extra.md").write_text("a file the plot writes beside plot.png\n")


EXPERIMENT = Experiment(ToyConfig, run, plot, TIMINGS)


def register(monkeypatch) -> None:
    """Make ``experiment: toy`` a known experiment for the current test."""
    monkeypatch.setitem(EXPERIMENTS, NAME, EXPERIMENT)


def write_config(path: Path, sweep: list[str], out_dir: Path, **fields) -> Path:
    """A toy config file at ``path``: ``fields``, then the sweep entries (YAML flow maps)."""
    lines = [f"experiment: {NAME}", f"out_dir: {out_dir}"]
    lines += [f"{k}: {v}" for k, v in fields.items()]
    if sweep:
        lines += ["sweep:", *(f"  - {entry}" for entry in sweep)]
    path.write_text("\n".join(lines) + "\n")
    return path
