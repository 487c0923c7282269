"""How the final smoothing of a registered motion treats the video's ends, scored on the
registration's own unsmoothed roots.

``python -m experiments.smoothing_ends RUNS [RUNS ...] [--to PAGE]``

``RUNS`` are folders of :mod:`experiments.register_synthetic` run records made with the final
smoothing off, e.g. ``python -m experiments run experiments/configs/register_movements.yaml
out_dir=runs/smoothing_ends 'registration={refine.smooth_s: "0"}'``: each run's ``per_frame.csv`` holds
the registered root per video frame (``root_x`` .. ``root_z``, metres) beside the true one
(``root_true_x`` ..). Each of :data:`motion.smoothing.FITS` is applied to the registered root
at the registration's default ``refine.smooth_s`` (:func:`smoothed_root`), and scored against
the truth (:func:`score_root`) on what the movement check reads
(:mod:`motion.registration.movement`): the net displacement between the mean positions over
the end windows (``end_window_s``), the peak speed over windows of ``min_compared_s``, and
the position error over the frames near either end (where the kernel is cut) and inside.

What it shows: a Gaussian weighted mean cut at the ends pulls the first and last frames
toward the inside, so a root moving through the video is registered short of its travel
(the travel and gait checks read it too slow); a local linear fit keeps the trend to the
ends at the price of some noise there.
"""

from __future__ import annotations

import csv
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from experiments.summarise import SummariseError, load_runs, page_main, provenance_lines
from motion.registration.movement import MovementSettings, net_displacement_m, peak_speed
from motion.registration.refine import RefineSettings
from motion.smoothing import FITS, TRUNCATE_SIGMAS, smooth_values

__all__ = ["RootScore", "main", "page", "read_roots", "score_root", "smoothed_root"]

#: the kinds scored: the registration's own estimate, then each smoothing
KINDS = ("unsmoothed", *FITS)


@dataclass(frozen=True)
class RootScore:
    """One root path against the truth.

    Attributes:
        net_err_pct: the net displacement's error, percent of the true one (NaN where the
            truth moves less than the movement check's ``travelling_m``: nothing to read).
        peak_err_pct: the peak speed's error, percent of the true peak (NaN where the true
            peak is under 0.4 m/s or the video is shorter than a window).
        end_err_m: the mean position error over the frames the kernel is cut at (metres).
        inside_err_m: the same over the frames between.
    """

    net_err_pct: float
    peak_err_pct: float
    end_err_m: float
    inside_err_m: float


def smoothed_root(root: Tensor, fps: float, kind: str) -> Tensor:
    """``(F, 3)`` ``root`` smoothed as the registration's final step does it at its default
    ``refine.smooth_s``, by ``kind`` (one of :data:`KINDS`; ``"unsmoothed"`` returns it)."""
    if kind == "unsmoothed":
        return root.clone()
    return smooth_values(root, RefineSettings().smooth_s * fps, fit=kind)


def score_root(root: Tensor, truth: Tensor, fps: float) -> RootScore:
    """``root`` and ``truth`` ``(F, 3)`` metres at ``fps`` video frames per second."""
    s = MovementSettings()
    frames = root.shape[0]
    k = max(1, round(s.end_window_s * fps))
    true_net = net_displacement_m(truth, k)
    net = (
        100 * (net_displacement_m(root, k) / true_net - 1)
        if true_net >= s.travelling_m
        else math.nan
    )
    window = max(2, round(s.min_compared_s * fps))
    times = torch.arange(frames, dtype=torch.float64) / fps
    true_peak = peak_speed(truth, times, window, k)
    peak = (
        100 * (peak_speed(root, times, window, k) / true_peak - 1)
        if math.isfinite(true_peak) and true_peak >= 0.4
        else math.nan
    )
    cut = min(math.ceil(TRUNCATE_SIGMAS * RefineSettings().smooth_s * fps), frames // 2)
    error = (root - truth).norm(dim=-1)
    ends = torch.cat([error[:cut], error[frames - cut :]])
    inside = error[cut : frames - cut]
    return RootScore(
        net,
        peak,
        float(ends.mean()) if len(ends) else math.nan,
        float(inside.mean()) if len(inside) else math.nan,
    )


def read_roots(folder: Path) -> tuple[Tensor, Tensor]:
    """The registered and the true root ``(F, 3)`` of one run's ``per_frame.csv``."""
    with open(folder / "per_frame.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or "root_true_x" not in rows[0]:
        raise SummariseError(
            f"{folder}: per_frame.csv has no root_true_x column (rerun register_synthetic)"
        )

    def path(prefix: str) -> Tensor:
        return torch.tensor(
            [[float(r[f"{prefix}_{a}"]) for a in "xyz"] for r in rows], dtype=torch.float64
        )

    return path("root"), path("root_true")


def _student(config: dict) -> str:
    return Path(config.get("student") or config.get("reference", "")).stem or "?"


def _percent(x: float) -> str:
    return f"{x:+.1f}" if math.isfinite(x) else "--"


def _metres(x: float) -> str:
    return f"{x:.2f}" if math.isfinite(x) else "--"


def page(sources: Sequence[str]) -> str:
    """The results page over every run recorded under ``sources``.

    Raises:
        SummariseError: a run that was smoothed, or that lacks the root columns.
    """
    runs = [run for source in sources for run in load_runs(source)]
    table = []
    for run in runs:
        smooth = str(run.config.get("registration", {}).get("refine.smooth_s", ""))
        if smooth.strip() not in ("0", "0.0"):
            raise SummariseError(
                f"{run.folder}: registered with the final smoothing on (set registration: "
                '{refine.smooth_s: "0"}: the page applies each smoothing itself)'
            )
        root, truth = read_roots(run.folder)
        fps = float(run.config["fps"])
        scores = [score_root(smoothed_root(root, fps, kind), truth, fps) for kind in KINDS]
        label = f"{_student(run.config)}, warp seed {run.config.get('warp_seed', '?')}"
        table.append((label, scores))
    lines = [
        "# The registered root at the video's ends: weighted mean or local linear fit",
        "",
        f"Generated by `python -m experiments.smoothing_ends {' '.join(sources)}` from "
        "register_synthetic run records made with the final smoothing off "
        '(`registration: {refine.smooth_s: "0"}`); each smoothing applied to their registered '
        f"roots at the default `refine.smooth_s` ({RefineSettings().smooth_s:g} s).",
        "",
        *provenance_lines(runs),
        "",
        "Net: the net displacement's error (percent of the true one; the mean positions over "
        "the movement check's end windows; -- where the truth moves under "
        f"{MovementSettings().travelling_m:g} m). Peak: the peak speed's error over "
        f"{MovementSettings().min_compared_s:g} s windows (percent; -- under 0.4 m/s). "
        "Ends / inside: the mean position error (m) over the frames the kernel is cut at, "
        "and between.",
        "",
        "| student | "
        + " | ".join(f"net, {k}" for k in KINDS)
        + " | "
        + " | ".join(f"peak, {k}" for k in KINDS)
        + " | "
        + " | ".join(f"ends / inside, {k}" for k in KINDS)
        + " |",
        "|---|" + "---|" * (3 * len(KINDS)),
    ]
    for label, scores in table:
        lines.append(
            f"| {label} | "
            + " | ".join(_percent(s.net_err_pct) for s in scores)
            + " | "
            + " | ".join(_percent(s.peak_err_pct) for s in scores)
            + " | "
            + " | ".join(f"{_metres(s.end_err_m)} / {_metres(s.inside_err_m)}" for s in scores)
            + " |"
        )

    def mean(values: list[float], absolute: bool = False) -> str:
        finite = [abs(v) if absolute else v for v in values if math.isfinite(v)]
        return f"{np.mean(finite):+.1f}" if finite else "--"

    nets = [[scores[i].net_err_pct for _, scores in table] for i in range(len(KINDS))]
    lines += [
        "",
        "Over the runs whose truth travels: the net displacement's mean error (its bias) and "
        "mean absolute error, percent:",
        "",
        "| | " + " | ".join(KINDS) + " |",
        "|---|" + "---|" * len(KINDS),
        "| mean | " + " | ".join(mean(n) for n in nets) + " |",
        "| mean absolute | " + " | ".join(mean(n, absolute=True).lstrip("+") for n in nets) + " |",
        "",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    return page_main(argv, "python -m experiments.smoothing_ends", __doc__.split("\n\n")[0], page)


if __name__ == "__main__":
    sys.exit(main())
