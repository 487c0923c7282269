"""Posture refinement against the start noise (the proposal's Figs. 16-17).

The protocol of :mod:`experiments.nbp_single_image` at each start noise level (degrees of
uniform noise on every angle of every part's joint): mean E_2D and E_3D of the start and of
the result per level, and the curves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from experiments import nbp_single_image
from experiments.config import ExperimentConfig
from experiments.progress import progress
from motion.settings import setting

#: metrics that are timings (timings.json)
TIMINGS = ("sec_per_frame",)


@dataclass
class NbpNoiseSweepConfig(ExperimentConfig):
    """Fields of ``experiments/configs/nbp_noise_sweep.yaml`` (the rest as
    ``nbp_single_image``'s defaults)."""

    NAME = "nbp_noise_sweep"
    TINY_DOC = (
        "a quick run: frames=2, particles=30, iterations=2, levels=[0, 30] (values given on "
        "the command line win)"
    )
    TINY: ClassVar[dict] = {"frames": 2, "particles": 30, "iterations": 2, "levels": [0.0, 30.0]}

    frames: int = setting(40, "frames taken evenly from the bundled walk", ge=1, le=10000)
    particles: int = setting(150, "particles per part", ge=2, le=5000)
    iterations: int = setting(6, "iterations per annealing run", ge=1, le=100)
    levels: list[float] = setting(
        [0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0], "start noise levels, degrees", ge=0, le=90
    )


def run(cfg: NbpNoiseSweepConfig):
    rows = {"noise_deg": [], "e2d_init": [], "e2d": [], "e3d_init": [], "e3d": []}
    seconds = []
    for level in progress(cfg.levels, "nbp_noise_sweep: noise levels"):
        single = nbp_single_image.NbpSingleImageConfig(
            frames=cfg.frames,
            particles=cfg.particles,
            iterations=cfg.iterations,
            noise_deg=level,
            seed=cfg.seed,
        )
        m, _, _ = nbp_single_image.run(single)
        rows["noise_deg"].append(level)
        for key in ("e2d_init", "e2d", "e3d_init", "e3d"):
            rows[key].append(m[f"{key}_mean"])
        seconds.append(m["sec_per_frame"])
    metrics = {"sec_per_frame": float(np.mean(seconds))}
    for level, e2, e3 in zip(rows["noise_deg"], rows["e2d"], rows["e3d"], strict=True):
        metrics[f"e2d_mean_at_{level:g}"] = e2
        metrics[f"e3d_mean_at_{level:g}"] = e3
    columns = {k: np.asarray(v) for k, v in rows.items()}
    return metrics, columns, {"columns": columns}


def plot(path, data, title: str) -> None:
    c = data["columns"]
    nbp_single_image.plot_errors(path, c["noise_deg"], c, "start noise (degrees)", title, "o")
