"""End-to-end demo: time alignment of a bundled motion against a warped, corrupted 'video'.

The proposal's Fig. 12 experiment on real motion capture: the reference is a CMU walk at
120 Hz; the input is the same motion resampled to 25 fps through a smooth non-linear time
warp, with noise, and with a stretch of frames replaced by later frames (as the proposal
replaces frames 40-50 by frames 50-60). Three aligners recover C: the proposal's DTW, exact
chain Viterbi, and the robust chain (bounded cost plus a slope prior). Until the image-based
pipeline lands, the per-frame features are the joint angles (sin/cos of every rotation
channel), standing in for the stick-figure distance of Eq. 24.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from motion.alignment import chain_align, dtw, robust_cost, slope_step_cost, soft_align
from motion.bundled import WALK_02_01
from motion.bvh import read_bvh

#: the demo's reference (:data:`motion.bundled.WALK_02_01`)
BUNDLED_BVH = WALK_02_01


def angle_features(bvh_path: Path) -> tuple[torch.Tensor, float]:
    """``(T, 2R)`` sin/cos of the R rotation channels of every frame, and the frame rate (Hz)."""
    bvh = read_bvh(bvh_path)
    motion = bvh.motion_frames()  # without the cgspeed converter's reference pose
    angles = np.deg2rad(motion[:, bvh.rotation_columns()])
    feats = np.concatenate([np.sin(angles), np.cos(angles)], axis=1)
    return torch.from_numpy(feats), bvh.frame_rate


def make_input(
    reference: torch.Tensor,
    ref_rate: float,
    video_rate: float,
    generator: torch.Generator,
    noise: float = 0.05,
    corrupt: tuple[float, float] | None = (0.4, 0.5),
) -> tuple[torch.Tensor, torch.Tensor, slice | None]:
    """Resample the reference through a smooth non-linear warp; optionally corrupt a stretch.

    Returns:
        video features ``(T', F)``, true correspondence ``(T',)`` long, the corrupted slice.
    """
    num_ref = reference.shape[0]
    num_video = int((num_ref - 1) * video_rate / ref_rate) + 1
    u = torch.linspace(0, 1, num_video, dtype=torch.float64)
    wobble = 0.04 * (1 + float(torch.rand(1, generator=generator)))
    warp = (u + wobble * torch.sin(2 * math.pi * u)) * (num_ref - 1)
    true = torch.cummax(warp.round().long().clamp(0, num_ref - 1), 0).values
    video = reference[true].clone()
    segment = None
    if corrupt is not None:
        lo, hi = (int(f * num_video) for f in corrupt)
        length = hi - lo
        video[lo:hi] = (
            reference[true[hi : hi + length]] if hi + length <= num_video else video[lo:hi]
        )
        segment = slice(lo, hi)
    video += noise * torch.randn(video.shape, generator=generator, dtype=video.dtype)
    return video, true, segment


def run_demo(
    bvh_path: Path = BUNDLED_BVH,
    out_dir: Path = Path("runs/demo"),
    seed: int = 0,
    video_rate: float = 25.0,
    max_step: int = 12,
) -> dict[str, float]:
    """Run the demo; writes ``metrics.json`` (accuracy: the same seed gives the same
    file), ``timings.json`` (``seconds_*``, wall times) and ``alignment.png`` under ``out_dir``.

    Returns:
        flat metrics: mean |C - C_true| (reference frames) per method, overall, outside and
        inside the corrupted stretch, plus the wall times (``seconds_<method>``).
    """
    generator = torch.Generator().manual_seed(seed)
    reference, ref_rate = angle_features(bvh_path)
    video, true, segment = make_input(reference, ref_rate, video_rate, generator)
    cost = (video[:, None, :] - reference[None, :, :]).square().mean(-1)  # (T', T)
    num_video, num_ref = cost.shape
    slope = (num_ref - 1) / (num_video - 1)

    estimates: dict[str, torch.Tensor] = {}
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    estimates["dtw"] = dtw(cost).choice
    timings["dtw"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    estimates["chain"] = chain_align(cost, max_step, fix_start=True, fix_end=True).path[0]
    timings["chain"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    robust = robust_cost(cost)
    prior = slope_step_cost(max_step, slope, 0.5 * float(robust.max())).to(cost.dtype)
    estimates["robust"] = chain_align(
        robust, max_step, fix_start=True, fix_end=True, step_cost=prior
    ).path[0]
    timings["robust"] = time.perf_counter() - t0
    soft = soft_align(
        robust,
        max_step,
        temperature=0.05 * float(robust.max()),
        fix_start=True,
        fix_end=True,
        step_cost=prior,
    )

    inside = torch.zeros(num_video, dtype=torch.bool)
    if segment is not None:
        inside[segment] = True
    metrics: dict[str, float] = {"num_video": num_video, "num_ref": num_ref}
    for name, est in estimates.items():
        err = (est - true).abs().double()
        metrics[f"c_err_mean_{name}"] = float(err.mean())
        metrics[f"c_err_outside_mean_{name}"] = float(err[~inside].mean())
        metrics[f"c_err_inside_mean_{name}"] = float(err[inside].mean()) if inside.any() else 0.0
        metrics[f"seconds_{name}"] = timings[name]
    metrics["soft_std_mean_robust"] = float(soft.std.mean())

    out_dir.mkdir(parents=True, exist_ok=True)
    accuracy = {k: v for k, v in metrics.items() if not k.startswith("seconds_")}
    seconds = {k: v for k, v in metrics.items() if k.startswith("seconds_")}
    (out_dir / "metrics.json").write_text(json.dumps(accuracy, indent=2, sort_keys=True) + "\n")
    (out_dir / "timings.json").write_text(json.dumps(seconds, indent=2, sort_keys=True) + "\n")
    _plot(
        out_dir / "alignment.png",
        true,
        estimates,
        soft.expected[0],
        soft.std[0],
        segment,
        bvh_path.name,
    )
    return metrics


def _plot(path, true, estimates, mean, std, segment, title) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    t = np.arange(len(true))
    if segment is not None:
        ax.axvspan(segment.start - 0.5, segment.stop - 0.5, color="0.9", label="replaced frames")
    ax.fill_between(
        t,
        (mean - 2 * std).numpy(),
        (mean + 2 * std).numpy(),
        color="C2",
        alpha=0.2,
        label="robust, posterior mean ± 2 std",
    )
    ax.plot(t, true.numpy(), "k-", lw=2, label="true C")
    styles = {
        "dtw": ("C3", "--", "proposal DTW (Eq. 26)"),
        "chain": ("C0", ":", "chain Viterbi"),
        "robust": ("C2", "-", "robust chain"),
    }
    for name, est in estimates.items():
        color, ls, label = styles[name]
        ax.plot(t, est.numpy(), color=color, ls=ls, lw=1.5, label=label)
    ax.set_xlabel("video frame t' (25 fps)")
    ax.set_ylabel("reference frame C(t') (120 Hz)")
    ax.set_title(f"Time alignment, {title}")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
