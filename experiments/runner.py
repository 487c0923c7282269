"""Run a config: one result record per run, written where tables and plots are made from it.

Each run writes into its ``out_dir``: ``metrics.json`` (flat: metric name -> number),
``config.yaml`` (the resolved config), ``per_frame.csv`` where the experiment has per-frame
values, ``plot.png`` and ``table.md``. A config with a ``sweep`` runs once per entry (into
``out_dir/<label>``) and also writes the combined ``table.md`` and ``metrics.json`` (keys
suffixed ``@label``) in ``out_dir``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import yaml
from tqdm import tqdm

from experiments import pose2sim_real, stick_pose, stick_time
from experiments.config import apply_overrides, load_config

__all__ = ["EXPERIMENTS", "run_config"]

#: experiment name -> (config schema, run function, plot function)
EXPERIMENTS = {
    "stick_time": (stick_time.StickTimeConfig, stick_time.run, stick_time.plot),
    "stick_pose": (stick_pose.StickPoseConfig, stick_pose.run, stick_pose.plot),
    "pose2sim_real": (pose2sim_real.Pose2simRealConfig, pose2sim_real.run, pose2sim_real.plot),
}


def _label(entry: dict) -> str:
    return ",".join(f"{k}={v}" for k, v in entry.items()) or "base"


def _write_run(out: Path, name: str, cfg, metrics: dict, columns: dict, plot_data, plot_fn) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True))
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
    plot_fn(out / "plot.png", plot_data, f"{name} ({out.name})")
    lines = ["| metric | value |", "|---|---|"] + [
        f"| {k} | {v:.4g} |" for k, v in sorted(metrics.items())
    ]
    (out / "table.md").write_text("\n".join(lines) + "\n")


def run_config(path: str | Path, overrides: dict | None = None) -> dict[str, float]:
    """Run a config file (with overrides); returns the flat metrics written to ``metrics.json``."""
    name, cfg, sweep = load_config(path, {k: v[0] for k, v in EXPERIMENTS.items()}, overrides)
    _, run_fn, plot_fn = EXPERIMENTS[name]
    out = Path(cfg.out_dir)
    if not sweep:
        metrics, columns, plot_data = run_fn(cfg)
        _write_run(out, name, cfg, metrics, columns, plot_data, plot_fn)
        return metrics
    combined: dict[str, float] = {}
    rows = []
    for entry in tqdm(sweep, desc=name, unit="run", disable=None):
        label = _label(entry)
        sub = apply_overrides(cfg, entry, where=f"sweep {label}")
        metrics, columns, plot_data = run_fn(sub)
        _write_run(
            out / label.replace("=", "-").replace(",", "_"),
            name,
            sub,
            metrics,
            columns,
            plot_data,
            plot_fn,
        )
        combined.update({f"{k}@{label}": v for k, v in metrics.items()})
        rows.append((label, metrics))
    keys = sorted({k for _, m in rows for k in m})
    table = ["| run | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    table += [
        "| " + label + " | " + " | ".join(f"{m.get(k, float('nan')):.4g}" for k in keys) + " |"
        for label, m in rows
    ]
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text("\n".join(table) + "\n")
    (out / "metrics.json").write_text(json.dumps(combined, indent=2, sort_keys=True))
    return combined
