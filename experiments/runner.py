"""Run a config: one result record per run, written where tables and plots are made from it.

Each run writes into its ``out_dir``: ``metrics.json`` (flat: metric name -> number, the
accuracy figures only, so the same config and seed give a byte-identical file),
``timings.json`` (the experiment's timing figures, e.g. ``poses_per_s``, which vary from run
to run; only for experiments that measure any), ``config.yaml`` (the resolved config),
``per_frame.csv`` where the experiment has per-frame values, ``plot.png`` and ``table.md``. A
config with a ``sweep`` runs once per entry (into ``out_dir/<label>``) and also writes the
combined ``table.md``, ``metrics.json`` and ``timings.json`` (keys suffixed ``@label``) in
``out_dir``. Progress goes to stdout (see :mod:`experiments.progress`).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import yaml

from experiments import (
    nbp_ablation,
    nbp_noise_sweep,
    nbp_single_image,
    pose2sim_real,
    stick_pose,
    stick_time,
)
from experiments.config import apply_overrides, load_config, sweep_label
from experiments.progress import note, progress

__all__ = ["CONFIGS", "EXPERIMENTS", "Experiment", "run_config", "split_timings"]

#: the shipped config files
CONFIGS = Path(__file__).resolve().parent / "configs"


class Experiment(NamedTuple):
    """A registered experiment: its config schema, ``run(cfg) -> (metrics, per-frame
    columns, plot data)``, ``plot(path, data, title)``, and the names of its metrics that
    are timings (written to ``timings.json``, apart from the accuracy figures)."""

    schema: type
    run: Callable
    plot: Callable
    timings: tuple[str, ...] = ()


#: experiment name -> Experiment
EXPERIMENTS = {
    "stick_time": Experiment(stick_time.StickTimeConfig, stick_time.run, stick_time.plot),
    "stick_pose": Experiment(
        stick_pose.StickPoseConfig, stick_pose.run, stick_pose.plot, stick_pose.TIMINGS
    ),
    "pose2sim_real": Experiment(
        pose2sim_real.Pose2simRealConfig, pose2sim_real.run, pose2sim_real.plot
    ),
    "nbp_ablation": Experiment(
        nbp_ablation.NbpAblationConfig, nbp_ablation.run, nbp_ablation.plot, nbp_ablation.TIMINGS
    ),
    "nbp_noise_sweep": Experiment(
        nbp_noise_sweep.NbpNoiseSweepConfig,
        nbp_noise_sweep.run,
        nbp_noise_sweep.plot,
        nbp_noise_sweep.TIMINGS,
    ),
    "nbp_single_image": Experiment(
        nbp_single_image.NbpSingleImageConfig,
        nbp_single_image.run,
        nbp_single_image.plot,
        nbp_single_image.TIMINGS,
    ),
}


def split_timings(metrics: dict, timings: tuple[str, ...]) -> tuple[dict, dict]:
    """``metrics`` -> (accuracy figures, timing figures), by the names in ``timings`` (a
    sweep's ``name@label`` keys go by their ``name``)."""
    accuracy, timing = {}, {}
    for key, value in metrics.items():
        (timing if key.split("@", 1)[0] in timings else accuracy)[key] = value
    return accuracy, timing


def _json(values: dict) -> str:
    return json.dumps(values, indent=2, sort_keys=True) + "\n"


def _table(header: str, values: dict) -> list[str]:
    return [f"| {header} | value |", "|---|---|"] + [
        f"| {k} | {v:.4g} |" for k, v in sorted(values.items())
    ]


def _dir_name(label: str) -> str:
    """A sweep entry's folder: its label with ``=`` -> ``-``, ``,`` -> ``_`` and anything
    that is not a plain file-name character (``/`` included) -> ``_``."""
    return re.sub(r"[^\w.+-]", "_", label.replace("=", "-").replace(",", "_"))


def _write_json(out: Path, accuracy: dict, timing: dict) -> None:
    (out / "metrics.json").write_text(_json(accuracy))
    if timing:
        (out / "timings.json").write_text(_json(timing))


def _write_run(out: Path, name: str, cfg, metrics: dict, exp: Experiment, columns, plot_data):
    out.mkdir(parents=True, exist_ok=True)
    accuracy, timing = split_timings(metrics, exp.timings)
    _write_json(out, accuracy, timing)
    (out / "config.yaml").write_text(
        yaml.safe_dump({"experiment": name, **dataclasses.asdict(cfg)}, sort_keys=False)
    )
    if columns:
        keys = list(columns)
        with open(out / "per_frame.csv", "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(keys)
            for row in zip(*(columns[k] for k in keys), strict=True):
                writer.writerow([int(v) if float(v).is_integer() else float(v) for v in row])
    exp.plot(out / "plot.png", plot_data, f"{name} ({out.name})")
    lines = _table("metric", accuracy) + (["", *_table("timing", timing)] if timing else [])
    (out / "table.md").write_text("\n".join(lines) + "\n")


def run_config(path: str | Path, overrides: dict | None = None) -> dict[str, float]:
    """Run a config file (with overrides, see :func:`experiments.config.load_config`);
    returns the flat figures written to ``metrics.json`` and ``timings.json`` together."""
    name, cfg, sweep = load_config(path, {k: v.schema for k, v in EXPERIMENTS.items()}, overrides)
    exp = EXPERIMENTS[name]
    out = Path(cfg.out_dir)
    start = time.perf_counter()
    note(f"{name}: {path} -> {out}" + (f" ({len(sweep)} runs)" if sweep else ""))
    if not sweep:
        metrics, columns, plot_data = exp.run(cfg)
        _write_run(out, name, cfg, metrics, exp, columns, plot_data)
        note(f"{name}: done in {time.perf_counter() - start:.1f} s")
        return metrics
    combined: dict[str, float] = {}
    rows = []
    for entry in progress(sweep, f"{name}: sweep"):
        label = sweep_label(entry)
        note(f"{name}: run {label}")
        sub = apply_overrides(cfg, entry, where=f"sweep {label}")
        metrics, columns, plot_data = exp.run(sub)
        _write_run(out / _dir_name(label), name, sub, metrics, exp, columns, plot_data)
        combined.update({f"{k}@{label}": v for k, v in metrics.items()})
        rows.append((label, split_timings(metrics, exp.timings)[0]))
    keys = sorted({k for _, m in rows for k in m})
    table = ["| run | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    table += [
        "| " + label + " | " + " | ".join(f"{m.get(k, float('nan')):.4g}" for k in keys) + " |"
        for label, m in rows
    ]
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text("\n".join(table) + "\n")
    _write_json(out, *split_timings(combined, exp.timings))
    note(f"{name}: done in {time.perf_counter() - start:.1f} s")
    return combined
