"""Stage 1's correspondence C over many draws of its random silhouette subsample: how often
the time alignment lands far from the truth, on one synthetic student.

Stage 1 (:func:`motion.registration.approximate.approximate_registration`) ranks each
(video frame, reference frame) pair by a fit against a random subsample of each image's
silhouette pixels (``Stage1Settings.observed_points``), drawn from the registration's seed.
Where the pair costs hardly tell alignments apart -- another performer's gait, seen by one
camera, matches the reference's cycles almost alike -- which path the time alignment picks
can hang on that draw. Stages 2-3 refine C only within ``RefineSettings.band`` reference
frames of stage 1's, so a stage-1 C farther off than that stays off: the registration fails
on that seed. One :func:`motion.registration.register` run per seed shows whether one seed
was lucky; this experiment draws ``draws`` seeds (``seed``, ``seed + 1``, ...) of stages 0-1
alone, exactly as :func:`~motion.registration.register` runs them, on one synthetic student
(:class:`~experiments.register_synthetic.SyntheticStudentConfig`, the same fields and truth
as :mod:`experiments.register_synthetic`), and scores each draw's C against the nearest
equally true one (:func:`~experiments.register_synthetic.true_correspondences`).

Metrics: ``c_err_mean_stage1`` (mean over draws of each draw's mean C error, reference
frames), ``c_err_median_stage1``, ``c_far_fraction`` (the share of draws whose mean C error
exceeds ``RefineSettings().band``: beyond what stage 3 refines), ``c_err_max_stage1``;
``sec_stage1`` (mean seconds per draw, stages 0-1). ``per_frame.csv``: the true C and each
draw's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from experiments.progress import note
from experiments.register_synthetic import (
    SyntheticStudentConfig,
    nearest_truth,
    registration_settings,
    synthetic_inputs,
)
from motion.registration.pipeline import approximate_stages
from motion.registration.refine import RefineSettings
from motion.registration.types import Reference, VideoFeatures
from motion.settings import setting

__all__ = ["TIMINGS", "Stage1DrawsConfig", "plot", "run", "stage1_c"]

TIMINGS = ("sec_stage1",)


@dataclass
class Stage1DrawsConfig(SyntheticStudentConfig):
    """Fields of ``experiments/configs/stage1_draws.yaml``."""

    NAME = "stage1_draws"
    TINY_DOC = "a quick run (8 frames, 2 draws)"
    TINY: ClassVar[dict] = {"frames": 8, "draws": 2}

    draws: int = setting(8, "seeds of stages 0-1 tried: seed, seed + 1, ...", ge=1, le=1000)


def stage1_c(
    reference: Reference, video: VideoFeatures, cfg: Stage1DrawsConfig, seed: int
) -> torch.Tensor:
    """``(T',)`` stage 1's C of ``video`` against ``reference`` under the registration's seed ``seed``: stages 0-1
    exactly as :func:`motion.registration.register` runs them
    (:func:`~motion.registration.pipeline.approximate_stages`), on the CPU."""
    settings = registration_settings(cfg, seed=seed)
    generator = torch.Generator().manual_seed(seed)
    return approximate_stages(reference, video, settings, generator).stage1.C


def run(cfg: Stage1DrawsConfig):
    inputs = synthetic_inputs(cfg)
    reference, video, truth = inputs.reference, inputs.video, inputs.truth
    note(f"stage1_draws: {video.num_frames} video frames, {cfg.draws} draws")
    paths, errors, seconds = [], [], []
    for draw in range(cfg.draws):
        t0 = time.perf_counter()
        c = stage1_c(reference, video, cfg, cfg.seed + draw)
        seconds.append(time.perf_counter() - t0)
        nearest = truth.C_alternatives[nearest_truth(c, truth.C_alternatives)]
        errors.append(float((c - nearest).abs().double().mean()))
        paths.append(c)
        note(f"stage1_draws: seed {cfg.seed + draw}: C error {errors[-1]:.1f} frames")
    err = np.array(errors)
    metrics = {
        "c_err_mean_stage1": float(err.mean()),
        "c_err_median_stage1": float(np.median(err)),
        "c_err_max_stage1": float(err.max()),
        "c_far_fraction": float((err > RefineSettings().band).mean()),
        "sec_stage1": float(np.mean(seconds)),
    }
    columns = {
        "frame": np.arange(video.num_frames),
        "c_true": truth.C.numpy(),
        **{f"c_seed_{cfg.seed + d}": p.numpy() for d, p in enumerate(paths)},
    }
    data = {"frame": columns["frame"], "truths": truth.C_alternatives.numpy(), "paths": paths}
    return metrics, columns, data


def plot(path, data, title: str) -> None:
    """Every equally true C (grey) and each draw's stage-1 C against the video frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4), dpi=100)
    for i, c in enumerate(data["truths"]):
        ax.plot(data["frame"], c, "-", color="0.6", lw=3, label="true C" if i == 0 else None)
    for i, c in enumerate(data["paths"]):
        ax.plot(data["frame"], c.numpy(), "-", lw=1, label="stage 1, each seed" if i == 0 else None)
    ax.set_xlabel("video frame t'")
    ax.set_ylabel("reference frame C(t')")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
