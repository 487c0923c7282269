"""The findings' method error, calibrated on students of other performers, and the findings
it lets through scored on pairs left out of the calibration.

``python -m experiments.findings_calibration RUNS [RUNS ...] [--write FILE] [--to PAGE]``

``RUNS`` are folders of :mod:`experiments.register_synthetic` run records (each run's
``per_frame.csv`` carries, per clinical coordinate, the estimated and the true difference and
the inference's uncertainty, and which frames are trusted; ``experiments/configs/
register_cross.yaml`` makes them). Per camera count and coordinate, the method's error is the
RMS over the trusted frames of every run of the estimated minus the true difference
(:func:`calibrate`): a finding's interval counts it beside the inference's uncertainty
(:class:`motion.registration.export.FindingSettings`). ``--write`` stores the table
(:class:`motion.registration.method_error.MethodError`; the package ships it as
``motion/registration/data/method_error.json``).

So that the score is not the calibration's own data read back, each pair of performers (both
directions: the same two skeletons) is scored with a table calibrated on the *other* pairs
(:func:`leave_pair_out`): the findings ``motion register`` would state
(:func:`motion.registration.export.stated_findings`, from the run's own angles) against the
truth (:func:`experiments.register_synthetic.finding_agreement`), beside the rules that trust
the inference alone (method error 0) and a flat 12 degrees. ``--to`` writes the page.

The page also splits each coordinate's error in two (:func:`error_parts`): the *timing* part,
the reference's angle at the true C minus at the registration's C (what a perfect estimate of
the student's posture would still get wrong), and the *posture* part, the student's estimated
angle minus its true one; and it shows the pelvis's sagittal tilt, which a silhouette hardly
sees, as one shared error of lumbar extension and both hips' flexion (:func:`pelvis_rows`).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from experiments.register_synthetic import finding_agreement, true_mean
from experiments.summarise import SummariseError, load_runs, provenance_lines, write_page
from motion.angles import COORDINATES, SegmentMap, clinical_angles
from motion.registration.export import (
    FALLBACK_METHOD_ERROR_DEG,
    FindingSettings,
    JointAngles,
    stated_findings,
)
from motion.registration.method_error import MethodError
from motion.registration.types import Reference

__all__ = [
    "AngleRun",
    "ErrorParts",
    "FindingError",
    "PelvisRow",
    "calibrate",
    "error_parts",
    "finding_errors",
    "leave_pair_out",
    "main",
    "pelvis_rows",
    "read_angle_run",
    "score_run",
]


@dataclass(frozen=True)
class AngleRun:
    """One registration's clinical-angle differences, read back from its record.

    Attributes:
        folder: the run's record.
        pair: ``(reference, student)`` file names (no folders).
        cameras: how many cameras saw the student.
        motions_match: the movement check's verdict (no finding is stated without it).
        coordinates: the ``K`` coordinates estimated.
        time_s: ``(T,)`` video seconds; trusted: ``(T,)`` bool, the frames findings read.
        estimate, truth: ``(T, K)`` degrees, the estimated and true difference.
        uncertainty: ``(T, K)`` degrees, the inference's (NaN where not measured).
        timing_error: ``(T, K)`` degrees, the reference's angle at the true C minus at the
            registration's C (``None`` when the record or the reference file lacks it).
    """

    folder: Path
    pair: tuple[str, str]
    cameras: int
    motions_match: bool
    coordinates: list[str]
    time_s: np.ndarray
    trusted: np.ndarray
    estimate: np.ndarray
    truth: np.ndarray
    uncertainty: np.ndarray
    timing_error: np.ndarray | None = None

    @property
    def performers(self) -> frozenset[str]:
        """The two motions, in either role: a pair and its reverse share skeletons."""
        return frozenset(self.pair)

    @property
    def frame_rate(self) -> float:
        return 1.0 / float(np.median(np.diff(self.time_s))) if len(self.time_s) > 1 else 1.0

    def findings(
        self,
        rules: FindingSettings,
        table: MethodError | None = None,
        motions_match: bool | None = None,
    ) -> list[dict]:
        """The run's largest differences as ``motion register`` states or withholds them
        (:func:`motion.registration.export.stated_findings`) under ``rules`` and the
        calibration ``table``; ``motions_match`` overrides the run's own verdict."""
        match = self.motions_match if motions_match is None else motions_match
        return stated_findings(
            self.angles(),
            torch.from_numpy(self.trusted),
            self.frame_rate,
            rules,
            self.cameras,
            match,
            table=table,
        )

    def angles(self) -> JointAngles:
        """The run's :class:`JointAngles` as far as findings read them (differences,
        uncertainties, times; the postures themselves are not recorded)."""
        diff = torch.from_numpy(self.estimate)
        nan = torch.full_like(diff, math.nan)
        return JointAngles(
            coordinates=list(self.coordinates),
            time_s=torch.from_numpy(self.time_s),
            reference_deg=nan,
            student_deg=nan,
            difference_deg=diff,
            articulation_deg=nan,
            uncertainty_deg=torch.from_numpy(self.uncertainty),
        )


def read_angle_run(folder: Path, config: dict, motions_match: bool) -> AngleRun | None:
    """The angles of the run recorded in ``folder`` (``None`` when its ``per_frame.csv``
    has no coordinate columns: a record older than them)."""
    with open(folder / "per_frame.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    names = [k.removeprefix("diff_") for k in (rows[0] if rows else {}) if k.startswith("diff_")]
    if not names or "trusted" not in rows[0]:
        return None

    def column(key: str) -> np.ndarray:
        return np.array([float(r[key]) if r.get(key, "") != "" else math.nan for r in rows])

    def table(prefix: str) -> np.ndarray:
        return np.stack([column(f"{prefix}_{c}") for c in names], 1)

    timing = None
    if "c" in rows[0] and "c_true" in rows[0]:
        timing = _timing_error(str(config["reference"]), column("c"), column("c_true"), names)

    return AngleRun(
        folder=folder,
        pair=(Path(str(config["reference"])).name, Path(str(config.get("student") or "")).name),
        cameras=int(config["cameras"]),
        motions_match=motions_match,
        coordinates=names,
        time_s=column("time_s"),
        trusted=column("trusted") > 0.5,
        estimate=table("diff"),
        truth=table("true"),
        uncertainty=table("unc")
        if f"unc_{names[0]}" in rows[0]
        else np.full((len(rows), len(names)), math.nan),
        timing_error=timing,
    )


_REFERENCE_ANGLES: dict[str, np.ndarray] = {}


def _reference_angles(path: str) -> np.ndarray | None:
    """``(frames, len(COORDINATES))`` the clinical angles of the reference file at ``path``
    (relative to the working directory, as the configs name it), degrees; ``None`` when it
    cannot be read. Read once per file."""
    if path not in _REFERENCE_ANGLES:
        try:
            body = Reference.from_bvh(path)
        except (OSError, ValueError):
            return None
        segments = SegmentMap.from_roles(body.skeleton, body.model.mapping)
        angles = clinical_angles(body.skeleton, body.rotations.double(), segments)
        _REFERENCE_ANGLES[path] = angles.degrees.numpy()
    return _REFERENCE_ANGLES[path]


def _timing_error(path: str, c: np.ndarray, c_true: np.ndarray, names: list[str]):
    """``(T, K)`` the reference's angles at ``c_true`` minus at ``c`` (reference frames),
    wrapped to [-180, 180); ``None`` without the reference or with frames outside it."""
    angles = _reference_angles(path)
    if angles is None or not (np.isfinite(c).all() and np.isfinite(c_true).all()):
        return None
    c, c_true = c.astype(int), c_true.astype(int)
    if min(c.min(), c_true.min()) < 0 or max(c.max(), c_true.max()) >= len(angles):
        return None
    cols = [COORDINATES.index(name) for name in names]
    return _wrap(angles[c_true][:, cols] - angles[c][:, cols])


def _wrap(deg: np.ndarray) -> np.ndarray:
    return np.remainder(deg + 180.0, 360.0) - 180.0


def read_angle_runs(folders: Sequence[str | Path]) -> list[AngleRun]:
    """Every run of another performer (a ``student``) recorded under ``folders``."""
    out = []
    for folder in folders:
        for run in load_runs(folder):
            if not run.config.get("student"):
                continue
            angles = read_angle_run(
                run.folder, run.config, run.metrics.get("motions_match", 1) > 0.5
            )
            if angles is not None:
                out.append(angles)
    return out


def calibrate(runs: Sequence[AngleRun], source: str = "") -> MethodError:
    """Per camera count and coordinate, the RMS over the trusted frames of ``runs`` of the
    estimated minus the true difference, degrees (every frame of every run weighs the same;
    a coordinate with no finite frame is left out)."""
    degrees: dict[int, dict[str, float]] = {}
    frames: dict[int, dict[str, int]] = {}
    for cameras in sorted({r.cameras for r in runs}):
        errors: dict[str, list[np.ndarray]] = {}
        for run in (r for r in runs if r.cameras == cameras):
            err = (run.estimate - run.truth)[run.trusted]
            for k, name in enumerate(run.coordinates):
                errors.setdefault(name, []).append(err[:, k])
        for name, parts in errors.items():
            e = np.concatenate(parts)
            e = e[np.isfinite(e)]
            if len(e):
                degrees.setdefault(cameras, {})[name] = float(np.sqrt(np.mean(e**2)))
                frames.setdefault(cameras, {})[name] = len(e)
    return MethodError(degrees, source, frames)


@dataclass(frozen=True)
class ErrorParts:
    """One coordinate's error (estimated minus true difference), RMS over trusted frames,
    degrees, and its two parts: ``timing`` (the reference's angle at the true C minus at the
    registration's C) and ``posture`` (the student's estimated angle minus its true one);
    ``total = posture + timing`` frame by frame, so the RMS add only where the two are
    uncorrelated. ``frames`` counts the frames."""

    total: float
    timing: float
    posture: float
    frames: int


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else math.nan


def error_parts(runs: Sequence[AngleRun]) -> dict[int, dict[str, ErrorParts]]:
    """Per camera count and coordinate, the :class:`ErrorParts` over the trusted frames of
    the ``runs`` that know their timing error (the others are left out)."""
    out: dict[int, dict[str, ErrorParts]] = {}
    for cameras in sorted({r.cameras for r in runs}):
        parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        for run in (r for r in runs if r.cameras == cameras and r.timing_error is not None):
            err = _wrap(run.estimate - run.truth)[run.trusted]
            timing = run.timing_error[run.trusted]
            for k, name in enumerate(run.coordinates):
                ok = np.isfinite(err[:, k])
                parts.setdefault(name, []).append((err[ok, k], timing[ok, k]))
        for name, pieces in parts.items():
            err = np.concatenate([e for e, _ in pieces])
            timing = np.concatenate([t for _, t in pieces])
            out.setdefault(cameras, {})[name] = ErrorParts(
                _rms(err), _rms(timing), _rms(_wrap(err - timing)), len(err)
            )
    return out


#: the coordinates that one sagittal tilt of the pelvis moves together: tilting it forward
#: (the torso and thighs held) adds the same angle to lumbar extension and to each hip's
#: flexion, and the silhouette of a body whose pelvis is inside it hardly tells the two apart
PELVIS = ("lumbar_extension", "hip_flexion_r", "hip_flexion_l")


@dataclass(frozen=True)
class PelvisRow:
    """One pair and camera count's posture errors of :data:`PELVIS`, degrees.

    Attributes:
        pair: ``"reference against student"``. cameras: how many.
        means: the mean posture error of each of :data:`PELVIS` over trusted frames.
        hips_rms: the RMS posture error of the hips' flexion.
        trunk_thigh_rms: the RMS of the hips' flexion minus the lumbar extension (the angle
            between trunk and thigh, which the pelvis's tilt leaves unchanged).
    """

    pair: str
    cameras: int
    means: list[float]
    hips_rms: float
    trunk_thigh_rms: float


def pelvis_rows(runs: Sequence[AngleRun]) -> list[PelvisRow]:
    """A :class:`PelvisRow` per pair and camera count, from the runs that know their timing
    error and every coordinate of :data:`PELVIS`."""
    groups: dict[tuple[str, int], list[np.ndarray]] = {}
    for run in runs:
        if run.timing_error is None or not set(PELVIS) <= set(run.coordinates):
            continue
        cols = [run.coordinates.index(name) for name in PELVIS]
        posture = _wrap(_wrap(run.estimate - run.truth) - run.timing_error)[run.trusted][:, cols]
        key = (" against ".join(run.pair), run.cameras)
        groups.setdefault(key, []).append(posture[np.isfinite(posture).all(1)])
    out = []
    for (pair, cameras), pieces in sorted(groups.items()):
        e = np.concatenate(pieces)
        hips, lumbar = e[:, 1:], e[:, :1]
        out.append(PelvisRow(pair, cameras, e.mean(0).tolist(), _rms(hips), _rms(hips - lumbar)))
    return out


def score_run(run: AngleRun, rules: FindingSettings, table: MethodError | None = None) -> dict:
    """The findings ``motion register`` would state for ``run`` under ``rules`` (and the
    calibration ``table`` when ``rules.method_error_deg`` is none), scored against the truth
    (:func:`experiments.register_synthetic.finding_agreement`, and ``findings_found``: how
    many largest differences there were)."""
    found = run.findings(rules, table)
    truth = torch.from_numpy(run.truth)
    score = finding_agreement(found, torch.from_numpy(run.time_s), truth, run.coordinates)
    return score | {"findings_found": float(len(found))}


@dataclass(frozen=True)
class FindingError:
    """The error of the findings themselves on one coordinate: each run's largest
    differences (stated or not), their mean difference over their frames against the true
    mean there.

    Attributes:
        count: how many findings of the coordinate.
        rms: RMS of estimated minus true mean difference, degrees.
        mean: the mean of that error (its bias), degrees.
    """

    count: int
    rms: float
    mean: float


def finding_errors(runs: Sequence[AngleRun]) -> dict[int, dict[str, FindingError]]:
    """Per camera count and coordinate, :class:`FindingError` over the largest differences
    ``motion register`` picks in each run (:func:`motion.registration.export.
    stated_findings`, every rule's candidates: the inference alone, no bound)."""
    candidates = FindingSettings(method_error_deg=0.0, max_interval_deg=None)
    errors: dict[int, dict[str, list[float]]] = {}
    for run in runs:
        found = run.findings(candidates, motions_match=True)
        truth, time_s = torch.from_numpy(run.truth), torch.from_numpy(run.time_s)
        for finding in found:
            true = true_mean(finding, time_s, truth, run.coordinates)
            by_name = errors.setdefault(run.cameras, {})
            by_name.setdefault(finding["coordinate"], []).append(
                float(finding["mean_difference_deg"]) - true
            )
    return {
        cams: {
            name: FindingError(len(e), float(np.sqrt(np.mean(np.square(e)))), float(np.mean(e)))
            for name, e in by_name.items()
        }
        for cams, by_name in errors.items()
    }


def leave_pair_out(runs: Sequence[AngleRun]) -> list[tuple[AngleRun, MethodError]]:
    """Each run with the table calibrated on the runs of every *other* pair of performers
    (a pair and its reverse count as one)."""
    out = []
    for run in runs:
        others = [r for r in runs if r.performers != run.performers]
        out.append((run, calibrate(others) if others else MethodError({run.cameras: {}})))
    return out


#: the rules the page compares, each without the bound on the interval's width
#: (``max_interval_deg``) and with it (the default, :class:`FindingSettings`): the inference
#: alone, a flat error for every coordinate (the fallback), and the calibrated table (the one
#: made from the other pairs)
RULES = {
    "inference alone, no bound": FindingSettings(method_error_deg=0.0, max_interval_deg=None),
    f"flat {FALLBACK_METHOD_ERROR_DEG:g} degrees, no bound": FindingSettings(
        method_error_deg=FALLBACK_METHOD_ERROR_DEG, max_interval_deg=None
    ),
    "calibrated, no bound": FindingSettings(max_interval_deg=None),
    "inference alone, bound": FindingSettings(method_error_deg=0.0),
    "calibrated, bound (the default)": FindingSettings(),
}


@dataclass
class Tally:
    """Findings counted over runs: largest differences found, stated, stated that agree."""

    found: int = 0
    stated: int = 0
    agree: int = 0

    def add(self, score: dict) -> None:
        stated = int(score["findings_stated"])
        self.found += int(score["findings_found"])
        self.stated += stated
        if stated:
            self.agree += round(score["findings_agree_fraction"] * stated)

    def cells(self) -> str:
        agree = f"{self.agree / self.stated:.2f}" if self.stated else "--"
        withheld = f"{1 - self.stated / self.found:.2f}" if self.found else "--"
        return f"{self.stated} | {agree} | {withheld}"


def _tallies(runs: Sequence[AngleRun]) -> dict[tuple[str, int, str], Tally]:
    """Per (pair, cameras, rules) the tally of the findings; pair ``"all"`` pools them."""
    out: dict[tuple[str, int, str], Tally] = {}
    for run, table in leave_pair_out(runs):
        for name, rule in RULES.items():
            score = score_run(run, rule, table)
            for pair in (" against ".join(run.pair), "all"):
                out.setdefault((pair, run.cameras, name), Tally()).add(score)
    return out


def page(runs: Sequence[AngleRun], table: MethodError, sources: Sequence[str]) -> str:
    """The results page: the calibrated table, then the findings scored on left-out pairs."""
    cams = sorted(table.degrees)
    lines = [
        "# The findings' method error, calibrated on other performers",
        "",
        "Generated by `python -m experiments.findings_calibration "
        + " ".join(sources)
        + "` from register_synthetic run records of students of other performers.",
        "",
        *_provenance(sources),
        "",
        "## The method's error per coordinate",
        "",
        "RMS over the trusted frames of every run of the estimated minus the true difference of",
        "the clinical angle (student minus reference at the true C), degrees; the frames counted",
        "in brackets. `motion register` counts it in each finding's interval beside the",
        "inference's uncertainty (`findings.method_error_deg`; the package ships this table).",
        "",
        "| coordinate | " + " | ".join(f"{c} camera(s)" for c in cams) + " |",
        "|---|" + "---|" * len(cams),
    ]
    names = [c for c in COORDINATES if any(c in table.degrees[k] for k in cams)]
    for name in names:
        cells = []
        for k in cams:
            deg = table.degrees[k].get(name)
            n = table.frames.get(k, {}).get(name, 0)
            cells.append("--" if deg is None else f"{deg:.1f} ({n})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += _parts_section(runs)
    lines += _finding_error_section(runs)
    lines += [
        "",
        "## Findings on pairs left out of the calibration",
        "",
        "Each run's three largest differences (as `motion register` picks them), stated or",
        "withheld under each rule; a stated one agrees when its sign is the true one and it is",
        "within 5 degrees of the true mean difference over its frames. The calibrated rules",
        "read a table made from the *other* pairs of performers only (a pair and its reverse",
        "left out together); a bound withholds a finding whose interval is wider than ± 5",
        "degrees (`findings.max_interval_deg`). Columns: findings stated, the share of them",
        "that agree, the share of the largest differences withheld.",
        "",
        "| pair | cameras | rule | stated | agree | withheld |",
        "|---|---|---|---|---|---|",
    ]
    tallies = _tallies(runs)
    for (pair, cameras, rule), tally in sorted(
        tallies.items(), key=lambda kv: (kv[0][0] == "all", kv[0][0], kv[0][1])
    ):
        lines.append(f"| {pair} | {cameras} | {rule} | {tally.cells()} |")
    return "\n".join(lines) + "\n"


def _parts_section(runs: Sequence[AngleRun]) -> list[str]:
    """The page's account of where the error comes from (:func:`error_parts`,
    :func:`pelvis_rows`); empty when no run knows its timing error."""
    parts = error_parts(runs)
    if not parts:
        return []
    cams = sorted(parts)
    lines = [
        "",
        "## Where the error comes from",
        "",
        "Each coordinate's error split in two, RMS over the same trusted frames, degrees:",
        "*timing*, the reference's angle at the true C minus at the registration's C (what a",
        "perfect estimate of the student's posture would still get wrong: a fast joint's angle",
        "changes within the frames C is off by), and *posture*, the student's estimated angle",
        "minus its true one. The error is their sum frame by frame; their RMS add only where",
        "they are uncorrelated.",
        "",
        "| coordinate | "
        + " | ".join(f"{c} camera(s): total / timing / posture" for c in cams)
        + " |",
        "|---|" + "---|" * len(cams),
    ]
    for name in [c for c in COORDINATES if any(c in parts[k] for k in cams)]:
        cells = []
        for k in cams:
            p = parts[k].get(name)
            cells.append("--" if p is None else f"{p.total:.1f} / {p.timing:.1f} / {p.posture:.1f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    rows = pelvis_rows(runs)
    if rows:
        lines += [
            "",
            "### The pelvis's tilt",
            "",
            "Tilting the pelvis forward with the torso and thighs held adds one angle to lumbar",
            "extension and to both hips' flexion; the pelvis lies inside the silhouette, so the",
            "split between the three is barely seen. Where the posture errors of the three share",
            "their sign and size, the registration has the trunk and thighs but not the pelvis;",
            "the angle between trunk and thigh (hip flexion minus lumbar extension), which the",
            "tilt leaves unchanged, is then measured better than either.",
            "",
            "| pair | cameras | mean posture error: lumbar extension / hip flexion r / l "
            "| RMS: hip flexion | RMS: hip flexion - lumbar extension |",
            "|---|---|---|---|---|",
        ]
        for row in rows:
            mean = " / ".join(f"{m:+.1f}" for m in row.means)
            lines.append(
                f"| {row.pair} | {row.cameras} | {mean} | {row.hips_rms:.1f} "
                f"| {row.trunk_thigh_rms:.1f} |"
            )
    return lines


def _finding_error_section(runs: Sequence[AngleRun]) -> list[str]:
    """The page's table of :func:`finding_errors`."""
    errors = finding_errors(runs)
    lines = [
        "",
        "## The findings' own error",
        "",
        "The table above is per frame. A finding is a mean over a stretch, where part of the",
        "per-frame error (the timing's, which changes sign along a cycle) averages out. Per",
        "coordinate, over each run's three largest differences (stated or not): how many, the",
        "RMS of the finding's mean difference minus the true mean over its frames, and that",
        "error's mean (its bias), degrees. A rule calibrated on these instead would give an",
        "interval of at least twice the RMS: within ± 5 only for an RMS under 2.5.",
        "",
        "| cameras | coordinate | findings | RMS | bias |",
        "|---|---|---|---|---|",
    ]
    for cams in sorted(errors):
        by_name = errors[cams]
        for name in sorted(by_name, key=lambda n: (-by_name[n].count, n)):
            e = by_name[name]
            lines.append(f"| {cams} | {name} | {e.count} | {e.rms:.1f} | {e.mean:+.1f} |")
    return lines


def _provenance(sources: Sequence[str]) -> list[str]:
    return provenance_lines([run for source in sources for run in load_runs(source)])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.findings_calibration", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("runs", nargs="+", help="folders of register_synthetic run records")
    parser.add_argument("--write", help="write the calibrated table here (JSON)")
    parser.add_argument("--to", help="write the results page here (Markdown)")
    args = parser.parse_args(argv)
    try:
        runs = read_angle_runs(args.runs)
    except SummariseError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if not runs:
        print(
            f"error: {', '.join(args.runs)}: no run of another performer with per-coordinate "
            "columns in its per_frame.csv (rerun register_synthetic with student=...)",
            file=sys.stderr,
        )
        return 2
    source = f"{len(runs)} runs under {', '.join(args.runs)}"
    table = calibrate(runs, source)
    if args.write:
        table.write(args.write)
    text = page(runs, table, args.runs)
    write_page(text, args.to)
    return 0


if __name__ == "__main__":
    sys.exit(main())
