"""How well defined the true C between two performers is: the truth under several meanings of
"the same posture", and each registration's C scored against every one.

``python -m experiments.truth_definitions RUNS [RUNS ...] [--to PAGE] [--figure PNG]``

``RUNS`` are folders of :mod:`experiments.register_synthetic` run records of students of
*other performers* (``experiments/configs/register_cross.yaml`` makes them). For the reference
itself the true C is the one the student was rendered with. For another performer there is no
such C: :mod:`experiments.register_synthetic` defines it as the monotone alignment of the two
true 3-D motions that brings the joints, each in its root's frame, closest in metres
(:func:`~experiments.register_synthetic.true_correspondences`). Other definitions are as
reasonable (:data:`DISTANCES`): the same joints with each body's size divided out, the
directions of the bones (what a silhouette shows of a posture, whatever the bones' lengths),
or the joints' local rotations (what the articulation A compares). Two performers' postures
differ, so each definition puts the best match elsewhere.

The page shows, per synthetic student, how far each definition's true C lies from the
experiment's (mean over video frames, in reference frames, against the nearest of the
experiment's equally true alignments: :func:`truth_spread`); and per registration, its C and
stage 1's against each definition's truth (:func:`c_errors`). Where the definitions differ by
more than a C target, that target asks for more than the truth itself can say.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from experiments.register_synthetic import (
    SyntheticStudentConfig,
    clinical_angles_of,
    equally_true_alignments,
    nearest_truth,
    posture_cost,
    synth_config,
    truth_max_step,
)
from experiments.summarise import SummariseError, load_runs, page_main, provenance_lines
from motion.angles import COORDINATES
from motion.registration.types import Reference
from motion.synth import synthesize

__all__ = [
    "DISTANCES",
    "PairTruths",
    "RunC",
    "bone_direction_distance",
    "c_errors",
    "difference_spread",
    "figure_of",
    "local_rotation_distance",
    "main",
    "page",
    "page_of",
    "pair_truths",
    "read_runs",
    "scaled_position_distance",
    "truth_spread",
]


def _matched(student: Reference, reference: Reference) -> tuple[list[int], list[int]]:
    """Indices of the joints both skeletons name, in the student's order."""
    names = [n for n in student.skeleton.names if n in reference.skeleton.names]
    return (
        [student.skeleton.index(n) for n in names],
        [reference.skeleton.index(n) for n in names],
    )


def _height(motion: Reference) -> float:
    """Metres: the body's mean vertical extent over its frames (every 10th), root-normalised."""
    frames = torch.arange(0, motion.num_frames, 10)
    y = motion.body_frames(frames).positions[..., 1]
    return float((y.amax(-1) - y.amin(-1)).mean())


def scaled_position_distance(student: Reference, shown: Tensor, reference: Reference) -> Tensor:
    """``(T', T)``: :func:`~experiments.register_synthetic.posture_cost` with each body's
    joints divided by its height -- the same postures, whatever the two bodies' sizes."""
    si, ri = _matched(student, reference)
    a = student.body_frames(shown).positions[:, si] / _height(student)
    b = reference.body_frames(torch.arange(reference.num_frames)).positions[:, ri]
    b = b / _height(reference)
    return (a[:, None] - b[None]).norm(dim=-1).mean(-1)


def _segments(motion: Reference, positions: Tensor, joints: list[int]) -> Tensor:
    """``(..., J', 3)`` each joint's position minus its parent's."""
    parents = motion.skeleton.parents[joints]
    return positions[..., joints, :] - positions[..., parents, :]


def bone_direction_distance(student: Reference, shown: Tensor, reference: Reference) -> Tensor:
    """``(T', T)`` degrees: the mean angle between the two bodies' bones (parent joint to
    joint, each in its root's frame), over the bones both skeletons name with a length in
    both -- what a silhouette shows of a posture, whatever the bones' lengths."""
    si, ri = _matched(student, reference)
    with_parent = [k for k, j in enumerate(si) if int(student.skeleton.parents[j]) >= 0]
    si = [si[k] for k in with_parent]
    ri = [ri[k] for k in with_parent]
    keep = (student.skeleton.offsets[si].norm(dim=-1) > 1e-9) & (
        reference.skeleton.offsets[ri].norm(dim=-1) > 1e-9
    )
    si = [j for j, k in zip(si, keep.tolist(), strict=True) if k]
    ri = [j for j, k in zip(ri, keep.tolist(), strict=True) if k]
    a = _segments(student, student.body_frames(shown).positions, si)
    b = _segments(
        reference, reference.body_frames(torch.arange(reference.num_frames)).positions, ri
    )
    a = torch.nn.functional.normalize(a, dim=-1)
    b = torch.nn.functional.normalize(b, dim=-1)
    cos = (a[:, None] * b[None]).sum(-1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos)).mean(-1)


def local_rotation_distance(student: Reference, shown: Tensor, reference: Reference) -> Tensor:
    """``(T', T)`` degrees: the mean geodesic angle between the two motions' local rotations
    of the joints both name that rotate (not the root) -- the quantity the articulation A
    compares."""
    si, ri = _matched(student, reference)
    rotating = [
        k
        for k, (s, r) in enumerate(zip(si, ri, strict=True))
        if int(student.skeleton.parents[s]) >= 0
        and student.skeleton.rotation_orders[s]
        and reference.skeleton.rotation_orders[r]
    ]
    a = student.rotations[shown][:, [si[k] for k in rotating]].double()
    b = reference.rotations[:, [ri[k] for k in rotating]].double()
    trace = torch.einsum("aijk,bijk->abi", a, b)
    return torch.rad2deg(torch.acos(((trace - 1) / 2).clamp(-1.0, 1.0))).mean(-1)


#: The definitions of "the same posture" compared, each a ``(student, shown, reference) ->
#: (T', T)`` distance table; ``positions`` is the experiment's own truth.
DISTANCES: dict[str, Callable[[Reference, Tensor, Reference], Tensor]] = {
    "positions": posture_cost,
    "scaled_positions": scaled_position_distance,
    "bone_directions": bone_direction_distance,
    "local_rotations": local_rotation_distance,
}


@dataclass(frozen=True)
class PairTruths:
    """Every definition's equally true alignments of one synthetic student.

    Attributes:
        student, reference: the BVH files' names (no folders).
        warp_seed: the student's time warp.
        truths: per :data:`DISTANCES` name, ``(A, T')`` long reference frames, the best first.
        reference_angles: ``(T, K)`` degrees, the reference's clinical angles
            (:data:`motion.angles.COORDINATES`) in every frame.
    """

    student: str
    reference: str
    warp_seed: int
    truths: dict[str, Tensor]
    reference_angles: Tensor


def pair_truths(cfg: SyntheticStudentConfig) -> PairTruths:
    """The truths of ``cfg``'s student (another performer's BVH, rendered as
    :func:`~experiments.register_synthetic.synthetic_inputs` renders it, cut to
    ``cfg.frames``) under every definition in :data:`DISTANCES`."""
    if not cfg.student:
        raise ValueError("pair_truths: expected a student of another performer (student=...)")
    seq = synthesize(cfg.reference, synth_config(cfg), student=cfg.student, images=False)
    reference = Reference.from_bvh(cfg.reference)
    student = Reference.from_bvh(cfg.student)
    shown = torch.from_numpy(seq.arrays["C_shown"]).long()
    step = truth_max_step(shown)
    truths = {}
    for name, distance in DISTANCES.items():
        alternatives = equally_true_alignments(distance(student, shown, reference), step)
        truths[name] = alternatives[:, : cfg.frames] if cfg.frames else alternatives
    angles = clinical_angles_of(reference, reference.rotations).degrees
    return PairTruths(
        Path(cfg.student).name, Path(cfg.reference).name, cfg.warp_seed, truths, angles
    )


def _distance(c: Tensor, alternatives: Tensor) -> float:
    """Reference frames: mean ``|C - truth|`` against the nearest of ``alternatives``."""
    nearest = alternatives[nearest_truth(c, alternatives)]
    return float((c - nearest).abs().double().mean())


def truth_spread(truths: PairTruths) -> dict[str, float]:
    """Per definition, how far its best true C lies from the nearest of the experiment's
    (``positions``) equally true ones: mean over video frames, reference frames."""
    ours = truths.truths["positions"]
    return {name: _distance(t[0], ours) for name, t in truths.truths.items()}


def difference_spread(truths: PairTruths) -> dict[str, Tensor]:
    """Per definition, ``(T', K)`` degrees: how much the student's true clinical-angle
    difference (its angle minus the reference's at the true C) changes when the true C is
    that definition's best instead of the nearest of the experiment's: the reference's angle
    at the experiment's C minus at the definition's, wrapped to [-180, 180)."""
    ours = truths.truths["positions"]
    angles = truths.reference_angles
    out = {}
    for name, t in truths.truths.items():
        theirs = t[0]
        mine = ours[nearest_truth(theirs, ours)]
        out[name] = torch.remainder(angles[mine] - angles[theirs] + 180.0, 360.0) - 180.0
    return out


def c_errors(c: Tensor, truths: PairTruths) -> dict[str, float]:
    """Per definition, the C error of ``c`` ``(T',)`` against the nearest of its equally
    true alignments (reference frames, mean over video frames)."""
    return {name: _distance(c, t) for name, t in truths.truths.items()}


@dataclass(frozen=True)
class RunC:
    """One registration's C, read back from its record, scored against every definition."""

    folder: Path
    cameras: int
    seed: int
    truths: PairTruths
    final: dict[str, float]  # c_errors of the registration's C
    stage1: dict[str, float]  # c_errors of stage 1's C


def _config(doc: dict) -> SyntheticStudentConfig:
    fields = {f.name for f in dataclasses.fields(SyntheticStudentConfig)}
    return SyntheticStudentConfig(**{k: v for k, v in doc.items() if k in fields})


def _column(folder: Path, name: str) -> Tensor:
    with open(folder / "per_frame.csv", newline="") as fh:
        return torch.tensor([int(float(row[name])) for row in csv.DictReader(fh)])


def read_runs(folders: Sequence[str | Path]) -> list[RunC]:
    """Every run of another performer under ``folders``, scored; one :class:`PairTruths`
    per distinct synthetic student."""
    cache: dict[tuple, PairTruths] = {}
    out = []
    for folder in folders:
        for run in load_runs(folder):
            if not run.config.get("student") or not (run.folder / "per_frame.csv").exists():
                continue
            cfg = _config(run.config)
            key = (cfg.student, cfg.reference, cfg.warp_seed, cfg.warp, cfg.fps, cfg.frames)
            if key not in cache:
                cache[key] = pair_truths(cfg)
            truths = cache[key]
            out.append(
                RunC(
                    run.folder,
                    cfg.cameras,
                    int(run.config.get("seed", 0)),
                    truths,
                    c_errors(_column(run.folder, "c"), truths),
                    c_errors(_column(run.folder, "c_stage1"), truths),
                )
            )
    return out


def _pair(t: PairTruths) -> str:
    return f"{Path(t.student).stem} against {Path(t.reference).stem}"


def _cell(values: Sequence[float]) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.mean():.2f}" if len(v) == 1 else f"{v.mean():.2f} ± {v.std(ddof=1):.2f}"


def page(runs: Sequence[RunC], sources: Sequence[str]) -> str:
    """The results page of ``runs`` (read from the folders ``sources``): the truths' spread
    per synthetic student, what it does to the true differences, and each registration's C
    against every definition."""
    names = list(DISTANCES)
    students = {(r.truths.student, r.truths.reference, r.truths.warp_seed): r.truths for r in runs}
    lines = [
        "# How well defined the true C between two performers is",
        "",
        "Generated by `python -m experiments.truth_definitions "
        + " ".join(sources)
        + "` from register_synthetic run records of students of other performers.",
        "",
        *provenance_lines([run for source in sources for run in load_runs(source)]),
        "",
        "The true C of another performer is the monotone alignment that brings the two",
        'motions\' postures closest; what "closest" means is a choice. `positions` is the',
        "experiment's (joints in the root's frame, metres); `scaled_positions` divides each",
        "body by its height; `bone_directions` compares the bones' directions (what a",
        "silhouette shows, whatever their lengths); `local_rotations` the joints' local",
        "rotations (what A compares). Each keeps the alignments within 10 % of its best",
        "(another gait cycle) as equally true.",
        "",
        "## The truths' spread",
        "",
        "Per synthetic student: each definition's best C against the nearest of the",
        "experiment's equally true ones, mean over video frames, reference frames.",
        "",
        "| student | warp seed | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for (_, _, warp), truths in sorted(students.items()):
        spread = truth_spread(truths)
        cells = " | ".join(f"{spread[n]:.1f}" for n in names)
        lines.append(f"| {_pair(truths)} | {warp} | {cells} |")
    lines += ["", *_difference_section(list(students.values()))]
    lines += [
        "",
        "## Each registration's C against each truth",
        "",
        "Mean ± standard deviation over the runs (seeds and warps) of the mean C error, in",
        "reference frames, against the nearest of each definition's equally true alignments:",
        "the registration's final C, then stage 1's; `nearest` is, per run, the smallest of",
        "the four.",
        "",
        "| student | cameras | n | "
        + " | ".join(names)
        + " | nearest | stage 1: "
        + " | ".join(names)
        + " |",
        "|---|---|---|" + "---|" * (2 * len(names) + 1),
    ]
    groups: dict[tuple[str, int], list[RunC]] = {}
    for r in runs:
        groups.setdefault((_pair(r.truths), r.cameras), []).append(r)
    for (pair, cameras), group in sorted(groups.items()):
        final = " | ".join(_cell([r.final[n] for r in group]) for n in names)
        nearest = _cell([min(r.final.values()) for r in group])
        stage1 = " | ".join(_cell([r.stage1[n] for r in group]) for n in names)
        lines.append(f"| {pair} | {cameras} | {len(group)} | {final} | {nearest} | {stage1} |")
    return "\n".join(lines) + "\n"


def _difference_section(students: Sequence[PairTruths]) -> list[str]:
    """The page's table of :func:`difference_spread`, per coordinate, pooled over
    ``students``."""
    others = [n for n in DISTANCES if n != "positions"]
    spreads = [difference_spread(t) for t in students]
    lines = [
        "## What the definition does to the true differences",
        "",
        "A finding compares the student with the reference at the true C, so the true",
        "difference of a clinical angle changes with the definition: by the reference's angle",
        "at the experiment's true C minus at the definition's. Per coordinate, pooled over the",
        "synthetic students above: the RMS of that change over every video frame, then the mean",
        "over students of its mean over the video, absolute (what a finding over a long",
        "stretch sees), degrees.",
        "",
        "| coordinate | " + " | ".join(f"{n}: per frame / video mean" for n in others) + " |",
        "|---|" + "---|" * len(others),
    ]
    for k, coordinate in enumerate(COORDINATES):
        cells = []
        for name in others:
            frames = torch.cat([s[name][:, k] for s in spreads])
            means = torch.stack([s[name][:, k].mean().abs() for s in spreads])
            cells.append(f"{float(frames.square().mean().sqrt()):.1f} / {float(means.mean()):.1f}")
        lines.append(f"| {coordinate} | " + " | ".join(cells) + " |")
    return lines


@functools.lru_cache(maxsize=2)
def _scored(folders: tuple[str, ...]) -> tuple[RunC, ...]:
    """:func:`read_runs` of ``folders``, read once for the page and the figure.

    Raises:
        SummariseError: no folder of records, or no run of another performer in them.
    """
    runs = tuple(read_runs(folders))
    if not runs:
        raise SummariseError(
            f"{', '.join(folders)}: no run of another performer with a per_frame.csv "
            "(rerun register_synthetic with student=...)"
        )
    return runs


def page_of(folders: Sequence[str]) -> str:
    """The results page of the run records under ``folders`` (:func:`page`).

    Raises:
        SummariseError: no folder of records, or no run of another performer in them.
    """
    return page(_scored(tuple(folders)), folders)


def figure_of(folders: Sequence[str], path: str | Path) -> None:
    """Draw, for the run under ``folders`` whose truths lie farthest apart (the first such in
    name order), every definition's best true C, the registration's C and stage 1's against
    the video frame, to the PNG ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = _scored(tuple(folders))
    run = max(runs, key=lambda r: max(truth_spread(r.truths).values()))
    fig, ax = plt.subplots(figsize=(6.5, 4), dpi=100)
    for name, truths in run.truths.truths.items():
        ax.plot(truths[0].numpy(), lw=2.5, alpha=0.7, label=f"true C: {name}")
    ax.plot(_column(run.folder, "c").numpy(), "k-", lw=1.2, label="registration")
    ax.plot(_column(run.folder, "c_stage1").numpy(), "k--", lw=1, label="stage 1")
    ax.set_xlabel("video frame t'")
    ax.set_ylabel("reference frame C(t')")
    ax.set_title(
        f"{_pair(run.truths)}, {run.cameras} camera(s), warp seed {run.truths.warp_seed}, "
        f"seed {run.seed}",
        fontsize=9,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    return page_main(
        argv,
        "python -m experiments.truth_definitions",
        __doc__.split("\n\n")[0],
        page_of,
        figure_of,
    )


if __name__ == "__main__":
    sys.exit(main())
