"""Ablations of posture refinement: one Markdown table, a row per variant.

Each row is the :mod:`experiments.nbp_single_image` protocol with one change from the full
method (its defaults): annealing off, occlusion-unaware observations (each part scored
alone), the cues one by one, the one-way intensity cue, one search instead of the best of
four, the BPMC-style proposal, the particle count, the number of
cameras, temporal edges, the gradient polish. Columns: E_2D, E_3D (Eqs. 36-37, means over
the frames) and seconds per frame. Written as ``ablation.md`` beside the record.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from experiments import nbp_single_image
from experiments.config import ExperimentConfig
from experiments.progress import progress
from motion.settings import setting

#: variant name -> (row label, overrides of nbp_single_image's defaults)
VARIANTS: dict[str, tuple[str, dict]] = {
    "full": (
        "full method (silhouette + edges + two-way intensity, mixture proposal, 150 "
        "particles, best of 4 searches)",
        {},
    ),
    "no_annealing": ("no annealing", {"annealing": False}),
    "occlusion_unaware": ("occlusion-unaware observation (each part alone)", {"occlusion": False}),
    "silhouette": ("silhouette only", {"cues": ["silhouette"]}),
    "edges": ("silhouette + edges", {"cues": ["silhouette", "edges"]}),
    "joints": (
        "+ 2-D joints (2 px detector noise)",
        {"cues": ["silhouette", "edges", "intensity", "joints"]},
    ),
    "intensity_one_way": (
        "intensity one-way (a part's own colour cost only)",
        {"intensity_two_way": False},
    ),
    "one_search": ("one search (no choice among 4 by the image residual)", {"starts": 1}),
    "limits": ("+ joint-angle limits (cmu_cgspeed)", {"limits": "cmu_cgspeed"}),
    "bpmc": ("BPMC-style proposal (own marginal only)", {"proposal": "own"}),
    "particles_50": ("50 particles", {"particles": 50}),
    "particles_500": ("500 particles", {"particles": 500}),
    "cameras_2": ("2 cameras", {"cameras": 2}),
    "cameras_4": ("4 cameras", {"cameras": 4}),
    "temporal": ("temporal edges on (consecutive frames)", {"temporal": True}),
    "polish": ("gradient polish on", {"polish": True}),
}
#: metrics that are timings (timings.json)
TIMINGS = tuple(f"sec_per_frame_{v}" for v in VARIANTS)


@dataclass
class NbpAblationConfig(ExperimentConfig):
    """Fields of ``experiments/configs/nbp_ablation.yaml``."""

    NAME = "nbp_ablation"
    TINY_DOC = (
        "a quick run: frames=2, particles_scale=0.2, variants=[full, occlusion_unaware, bpmc] "
        "(values given on the command line win)"
    )
    TINY: ClassVar[dict] = {
        "frames": 2,
        "particles_scale": 0.2,
        "variants": ["full", "occlusion_unaware", "bpmc"],
    }

    frames: int = setting(40, "frames per variant", ge=1, le=10000)
    particles_scale: float = setting(
        1.0, "multiplies every variant's particle count (tests: fewer)", gt=0, le=10
    )
    variants: list[str] = setting(
        list(VARIANTS), "rows of the table", choices=tuple(VARIANTS), min_length=1
    )
    repeats: int = setting(
        1, "seeds per variant (seed, seed + 1, ...): rows show mean +- std", ge=1, le=20
    )


def run(cfg: NbpAblationConfig):
    metrics: dict[str, float] = {}
    rows = []
    for name in progress(cfg.variants, "nbp_ablation: variants"):
        label, overrides = VARIANTS[name]
        base = overrides.get("particles", nbp_single_image.NbpSingleImageConfig.particles)
        runs = []
        for seed in range(cfg.seed, cfg.seed + cfg.repeats):
            fields = {"frames": cfg.frames, "seed": seed, **overrides}
            fields["particles"] = max(2, round(base * cfg.particles_scale))
            runs.append(nbp_single_image.run(nbp_single_image.NbpSingleImageConfig(**fields))[0])
        mean = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        std = {k: float(np.std([r[k] for r in runs])) for k in runs[0]}
        metrics[f"e2d_mean_{name}"] = mean["e2d_mean"]
        metrics[f"e3d_mean_{name}"] = mean["e3d_mean"]
        metrics[f"sec_per_frame_{name}"] = mean["sec_per_frame"]
        rows.append((label, mean, std))
    spread = cfg.repeats > 1

    def cell(row, key):
        text = f"{row[1][key + '_init_mean']:.3f} -> {row[1][key + '_mean']:.3f}"
        return text + (f" +- {row[2][key + '_mean']:.3f}" if spread else "")

    seeds = f"seeds {cfg.seed}-{cfg.seed + cfg.repeats - 1}" if spread else f"seed {cfg.seed}"
    table = [
        f"| variant ({cfg.frames} frames, {seeds}) | E_2D (start -> result) | E_3D (start -> result) | s / frame |",
        "|---|---|---|---|",
        *(
            f"| {r[0]} | {cell(r, 'e2d')} | {cell(r, 'e3d')} | {r[1]['sec_per_frame']:.2f} |"
            for r in rows
        ),
    ]
    columns = {
        "variant": np.arange(len(rows)),
        "e2d": np.array([r[1]["e2d_mean"] for r in rows]),
        "e3d": np.array([r[1]["e3d_mean"] for r in rows]),
    }
    plot_rows = [(r[0], r[1]["e2d_mean"], r[1]["e3d_mean"]) for r in rows]
    return metrics, columns, {"table": "\n".join(table) + "\n", "rows": plot_rows}


def plot(path, data, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = data["rows"]
    fig, ax = plt.subplots(figsize=(9, 0.35 * len(rows) + 1.2), dpi=100)
    y = np.arange(len(rows))
    ax.barh(y - 0.2, [r[1] for r in rows], 0.4, label="E_2D", color="C3")
    ax.barh(y + 0.2, [r[2] for r in rows], 0.4, label="E_3D", color="C0")
    ax.set_yticks(y, [r[0][:48] for r in rows], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("fraction of the figure's height")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="x")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    Path(path).with_name("ablation.md").write_text(data["table"])
