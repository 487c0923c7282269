"""Does the student perform the reference's movement? Checked before any finding is stated.

A registration always returns a C, a T and an A, even for a student who runs while the
reference walks: the monotone chain finds the least bad path, and per-joint differences
then read the fit's failure as the student's style. This module decides, from the
registration itself, whether that happened. Each check is a physical property of one
movement performed by two people, with its threshold in :class:`MovementSettings`:

* **Travel.** Where the reference travels (a walk, a run), the student travels about as far
  over the same stretch of the reference: per cycle of the movement, i.e. one stride. One
  gait's stride length ranges over a factor ~1.6 between a slow and a brisk walker, and the
  registration's C may play the reference up to ~25 % too fast or slow on a periodic motion
  (which scales the stretch compared), so the ratio stays within a factor 2; a monocular
  depth estimate and one step's sway add some 0.2 m, so a difference under half a metre
  says nothing. A student who stays in place (a jump, a balance) against a walk, or covers
  2.5 times the ground per stride (a run), does not perform it; nor does one who travels
  metres while the matched stretch of the reference stays in place.
* **Back and forth.** Where the reference travels, the student goes the way it does: the
  student's path (root positions averaged over ``path_window_s`` windows, which averages a
  monocular depth estimate's frame-to-frame jitter out) is no less straight -- net
  displacement over path length -- than ``min_straightness`` times the reference's over the
  matched stretch. A walker's path on a curve stays straight by this measure (a quarter
  turn keeps 2 sqrt 2 / pi = 0.90 of its length, a U-turn 2 / pi = 0.64); a registered root
  that goes back and forth (0.3-0.45 on a basketball dribble against a walk, whose
  registered depth jumps between postures that do not fit, against 0.94-0.99 for walkers,
  real ones included) is another movement, or one the registration cannot follow: in
  either case no finding rests on it. The path is read only where the person is in view,
  not entering or leaving it (the silhouette off the image's left and right edges:
  ``check_movement``'s ``in_view``): a walker leaving the image has its depth placed on half
  a body, and the bundled demo's registered root swung 4 m in depth over its last 10 frames
  (0.43 as straight, read over the whole video).
* **Stalls.** Where the reference has to advance by two or more frames per video frame
  (its rate over the video's, times the fitted speed), a C that stands still on a fifth of
  the frames is stop-and-go: the chain held on to one posture because none of the next ones
  fitted.
* **Held ends.** A run of video frames at the start or the end that all match the first (last)
  reference moment C reaches is no stall: the video goes on where the reference's movement
  has not begun or has ended (another performer walks on past the stretch of the reference
  his phase matches), or the student waits. Such frames have no counterpart in the
  reference: they are left out of every check (up to ``max_held`` of the video; beyond that
  they count as stalls), no finding rests on them, and a warning says so.
* **Racing.** Advancing by twice the reference's own rate or more (reference frames per
  video frame over the ratio of the frame rates) on a quarter of the frames, the student
  moves twice as fast as the reference there: another tempo of movement, or another one (a
  real student speeds up smoothly, by tens of percent).

* **Pace.** Going through the reference's movement at under a quarter of its pace
  (``min_pace``: the least-squares slope of C, reference seconds per video second) is no
  performance of it at another tempo: the student holds one of its postures (stands while
  the reference walks) and C crawls to keep the least bad match. One movement's tempo varies
  between people by about a factor 2 (a walking cadence spans some 60 to 140 steps a
  minute); the stalls above are counted only where C should advance by two frames or more,
  so they cannot see a C that hardly advances at all. Taken over at least
  ``min_compared_s`` seconds.
* **Gait.** Walking and running are two movements: people walk below a Froude number
  ``v^2 / (g L)`` (``v`` the speed, ``L`` the standing hip height) of about 0.5 and run above
  it, whatever their size (Alexander, *Physiol. Rev.* 69, 1989; Kram, Domingo & Ferris,
  *J. Exp. Biol.* 200, 1997: the walk-run transition at Froude 0.5 under every gravity
  tried). Each performer's Froude number is taken over the compared stretch at their own
  clock (the student's over the video's seconds, the reference's over its own): one below
  ``walking_froude`` (0.3: 1.6 m/s for a 0.9 m leg, a brisk walk) and the other at or above
  ``running_froude`` (0.5) is a walk against a run. Between the two nothing is said (a race
  walker, a slow jogger). Measured over at least ``min_compared_s`` seconds, a stride or so, so
  that one step's surge averages out. Speed alone is still no criterion: a patient who
  walks at 0.5 m/s against a reference at 1.3 m/s walks. A movement can also change gait on
  the way (a run-up and a kick: a 2.7 m/s burst, then a stop, a walker's speed on average):
  each performer's *peak* Froude number, the largest over windows of ``min_compared_s``
  (half a window apart), says whether it runs at all; one that runs somewhere (a peak at or
  above ``running_froude``) against one that never leaves a walk (a peak below
  ``walking_froude``) is a walk against a run too. Walkers' registered peaks read 0.14-0.32,
  real ones included (subject 7's brisk walk peaks at 0.34 in truth: between the two, no
  verdict); a run-up and kick (CMU 10_03), 0.59.

Thresholds were set from the physics above and checked (not fitted) on synthetic students
of the bundled CMU motions and on the real videos; the measurements are in the closing
notes of issue 39 and docs/experiments.md. Speed ratio alone is not a criterion: a slow
student is a finding, not another movement.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
from torch import Tensor

from motion.angles import SegmentMap
from motion.kinematics import Skeleton
from motion.settings import SettingError, Settings, setting

__all__ = [
    "GRAVITY",
    "HIP_HEIGHT_PER_HIP_TO_ANKLE",
    "MovementCheck",
    "MovementSettings",
    "check_movement",
    "froude_number",
    "held_ends",
    "leg_length_m",
    "net_displacement_m",
    "path_straightness",
    "peak_speed",
]

#: m/s^2, for the Froude number
GRAVITY = 9.81

#: standing hip height (greater trochanter, 0.530 of stature) over the hip-to-ankle length
#: (0.530 - 0.039 of stature, the ankle's height being 0.039): Winter's segment lengths
#: (D. A. Winter, *Biomechanics and Motor Control of Human Movement*, 4th ed., 2009,
#: Fig. 4.1, after Drillis & Contini). The Froude number's ``L`` is the hip height.
HIP_HEIGHT_PER_HIP_TO_ANKLE = 0.530 / 0.491


@dataclass(frozen=True)
class MovementSettings(Settings):
    """Thresholds of :func:`check_movement` (see the module's docstring for their grounds).
    Every field is checked at construction (a bad value raises
    :class:`~motion.settings.SettingError`, a ``ValueError``, naming it)."""

    max_travel_ratio: float = setting(
        2.0,
        "the student's net displacement over the reference's (over the frames C covers, the "
        "reference scaled by G) may lie in [1 / r, r] for this r",
        gt=1,
    )
    travelling_m: float = setting(
        0.5,
        "travel is compared when the student or the reference moves at least this far "
        "(metres, net) over those frames, and the two displacements differ by more than "
        "min_travel_difference_m",
        ge=0,
    )
    min_travel_difference_m: float = setting(
        0.5,
        "travel is compared only when the two displacements differ by more than this (metres)",
        ge=0,
    )
    end_window_s: float = setting(
        0.12,
        "the displacements compare the mean positions over this many seconds at each end (a "
        "step's sway averaged out)",
        ge=0,
    )
    path_window_s: float = setting(
        0.25,
        "seconds: the paths' straightness compares root positions averaged over windows "
        "this long (a monocular depth estimate's frame-to-frame jitter averaged out)",
        gt=0,
    )
    min_straightness: float = setting(
        0.6,
        "where the reference travels, the student's path (net displacement over path "
        "length) is at least this times as straight as the reference's over the matched "
        "stretch (a U-turn keeps 2 / pi = 0.64 of its length)",
        gt=0,
        le=1,
    )
    max_stalled: float = setting(
        0.2,
        "largest fraction of video frames where C stands still, counted only where the "
        "nominal step is at least stall_min_step",
        gt=0,
        le=1,
    )
    stall_min_step: float = setting(
        2.0,
        "stalls are counted only where the nominal step (reference frames per video frame at "
        "the fitted speed) is at least this",
        ge=0,
    )
    fast_step_factor: float = setting(
        2.0,
        "a step of C of at least this times the reference's frame rate over the video's is racing",
        gt=1,
    )
    max_fast: float = setting(
        0.25, "largest fraction of the video's frames on which C may race", gt=0, le=1
    )
    max_held: float = setting(
        0.4,
        "largest fraction of the video's frames, at its start and end together, that may hold "
        "C's first or last reference frame and be left out of the checks and the findings "
        "(beyond it they count as stalls)",
        ge=0,
        lt=1,
    )
    held_warning_s: float = setting(
        0.25,
        "seconds: a held end at least this long gets a warning (a shorter one, a fraction of a "
        "step, is left out of the checks and the findings silently)",
        ge=0,
    )
    walking_froude: float = setting(
        0.3,
        "a performer whose Froude number v^2 / (g L) over the compared stretch (v the net "
        "speed, L the standing hip height) is below this walks or stands (0.3: 1.6 m/s for a "
        "0.9 m leg)",
        gt=0,
    )
    running_froude: float = setting(
        0.5,
        "a performer whose Froude number is at least this runs (the walk-run transition); "
        "one walking against one running is another movement",
        gt=0,
    )
    min_pace: float = setting(
        0.25,
        "the least pace (reference seconds per video second, C's slope) at which the student "
        "still performs the reference's movement rather than holding one of its postures",
        ge=0,
    )
    min_compared_s: float = setting(
        1.0,
        "seconds: the pace and the gait are compared only when the student's compared "
        "stretch lasts at least this (about one stride)",
        ge=0,
    )

    def validate(self) -> None:
        """Check every field, then that ``walking_froude < running_froude``."""
        super().validate()
        if not self.walking_froude < self.running_froude:
            raise SettingError(
                f"{type(self).__name__}: walking_froude must be below running_froude; got "
                f"{self.walking_froude} >= {self.running_froude}"
            )


@dataclass(frozen=True)
class MovementCheck:
    """The verdict and its evidence.

    Attributes:
        motions_match: no check failed.
        reasons: one sentence per failed check (empty when they match).
        student_travel_m: the student's net displacement, metres.
        reference_travel_m: the reference's over the frames C covers, scaled by G.
        stalled_fraction: video frames where C stands still (``None``: not checked, the
            nominal step is below :attr:`MovementSettings.stall_min_step`).
        fast_fraction: video frames where C advances at ``fast_step_factor`` times the
            reference's rate or more.
        speed_ratio: reference seconds per video second (least-squares slope of C).
        held_start, held_end: video frames at the start (end) that hold C's first (last)
            reference frame before (after) the one that matches it, left out of the checks
            (0 when the held frames exceed ``max_held``; then they count as stalls).
        warnings: sentences for the user about the held frames, and about a video too short
            for the pace, path and gait checks when no check failed (empty when none).
        student_straightness, reference_straightness: each root's net displacement over
            its path length over the compared stretch (:func:`path_straightness`; ``nan``:
            not measured, the stretch shorter than ``min_compared_s`` or than 3 windows).
        student_froude, reference_froude: each performer's Froude number over the compared
            stretch at their own clock (``nan``: not measured: no leg lengths given, the
            stretch shorter than ``min_compared_s``, or C standing still).
        student_froude_peak, reference_froude_peak: each performer's largest Froude number
            over windows of ``min_compared_s`` (``nan`` as above).
    """

    motions_match: bool
    reasons: list[str] = field(default_factory=list)
    student_travel_m: float = math.nan
    reference_travel_m: float = math.nan
    stalled_fraction: float | None = None
    fast_fraction: float = math.nan
    speed_ratio: float = math.nan
    held_start: int = 0
    held_end: int = 0
    warnings: list[str] = field(default_factory=list)
    student_froude: float = math.nan
    reference_froude: float = math.nan
    student_straightness: float = math.nan
    reference_straightness: float = math.nan
    student_froude_peak: float = math.nan
    reference_froude_peak: float = math.nan

    def to_dict(self) -> dict:
        return asdict(self)

    def read_from(self, caveat: str) -> MovementCheck:
        """The same verdict with ``caveat`` (what the evidence was read from, e.g.
        silhouettes known to miss parts of the body) after each reason."""
        reasons = [f"{reason} -- {caveat}" for reason in self.reasons]
        return replace(self, reasons=reasons)

    def held(self, n: int) -> Tensor:
        """``(n,)`` bool: the held video frames of a registration of ``n`` frames."""
        mask = torch.zeros(n, dtype=torch.bool)
        mask[: self.held_start] = True
        mask[n - self.held_end :] = True
        return mask


def held_ends(c: Tensor) -> tuple[int, int]:
    """``(start, end)``: how many video frames at the start of ``c`` ``(T',)`` repeat its
    first value before the last frame that has it, and at the end repeat its last value
    after the first frame that has it (the zero steps of C's leading and trailing runs)."""
    n = int(c.shape[0])
    steps = (c[1:] != c[:-1]).nonzero().flatten()
    if len(steps) == 0:  # C never moves: one run, all of it held
        return n - 1, 0
    return int(steps[0]), n - 2 - int(steps[-1])


def _held_warnings(start: int, end: int, video_rate: float, c: Tensor, least_s: float) -> list[str]:
    """The user's sentences on held ends of ``start`` and ``end`` frames (those of at least
    ``least_s`` seconds) of a C ``c`` (its matched stretch)."""
    out = []
    start = start if start / video_rate >= least_s else 0
    end = end if end / video_rate >= least_s else 0
    if start:
        out.append(
            f"the first {start} video frames ({start / video_rate:.2f} s) all match the "
            f"reference's frame {int(c[0])}, where the matched stretch begins: the student "
            "has not started the reference's movement there (or the reference begins later); "
            "no finding rests on them"
        )
    if end:
        out.append(
            f"the last {end} video frames ({end / video_rate:.2f} s) all match the "
            f"reference's frame {int(c[-1])}, where the matched stretch ends: the video goes on "
            "past the reference's movement (or the student stops); no finding rests on them"
        )
    return out


def net_displacement_m(positions: Tensor, k: int) -> float:
    """Metres between the mean of the first ``k`` and of the last ``k`` of ``(F, 3)``."""
    k = max(1, min(k, positions.shape[0] // 2 or 1))
    return float((positions[-k:].mean(0) - positions[:k].mean(0)).norm())


def path_straightness(positions: Tensor, window: int) -> tuple[float, float, float]:
    """``(straightness, net, path)`` of ``(F, 3)`` positions (metres) averaged over
    consecutive windows of ``window`` rows (a last partial window dropped): the distance
    between the first and last window means over the summed distances between consecutive
    ones (1: a straight line; 1 also for a path of no length)."""
    count = positions.shape[0] // window
    means = positions[: count * window].reshape(count, window, -1).mean(1)
    net = float((means[-1] - means[0]).norm()) if count else 0.0
    path = float((means[1:] - means[:-1]).norm(dim=-1).sum()) if count > 1 else 0.0
    return (net / path if path > 0 else 1.0), net, path


def leg_length_m(skeleton: Skeleton, offsets: Tensor, segments: SegmentMap) -> float:
    """The standing hip height of a body, metres (the Froude number's ``L``): the mean over
    both legs of the hip-to-knee and knee-to-ankle distances of the rest pose of ``offsets``
    ``(J, 3)`` metres (the skeleton's joint offsets, scaled as the body's), times
    :data:`HIP_HEIGHT_PER_HIP_TO_ANKLE`."""
    rest = torch.zeros(skeleton.num_joints, 3, dtype=torch.float64)
    offsets = offsets.detach().to(torch.float64).cpu()
    for j in range(1, skeleton.num_joints):  # parents come before their children
        rest[j] = rest[int(skeleton.parents[j])] + offsets[j]
    legs = []
    for side in (0, 1):
        hip, knee, ankle = (
            skeleton.index(segments.joint(segment, side)) for segment in ("thigh", "shank", "foot")
        )
        legs.append(float((rest[knee] - rest[hip]).norm() + (rest[ankle] - rest[knee]).norm()))
    return HIP_HEIGHT_PER_HIP_TO_ANKLE * sum(legs) / 2


def froude_number(speed_m_s: float, leg_m: float) -> float:
    """``v^2 / (g L)`` of a speed (m/s) and a standing hip height (m): dimensionless."""
    return speed_m_s**2 / (GRAVITY * leg_m)


def _gait(froude: float, s: MovementSettings) -> str | None:
    """``"walk"`` (or stand), ``"run"``, or ``None`` between the two thresholds."""
    if froude < s.walking_froude:
        return "walk"
    return "run" if froude >= s.running_froude else None


def peak_speed(positions: Tensor, times_s: Tensor, window: int, ends: int) -> float:
    """The largest net speed (m/s) of ``(F, 3)`` positions at ``(F,)`` times (seconds) over
    windows of ``window`` rows, half a window apart: each window's distance between the means
    of its first and last ``ends`` rows over the time between their mean times (windows whose
    time does not advance are skipped; ``nan`` when none is left)."""
    if positions.shape[0] < window:
        return math.nan
    hop = max(1, window // 2)
    places = positions.unfold(0, window, hop)  # (W, 3, window)
    times = times_s.unfold(0, window, hop)  # (W, window)
    moved = (places[..., -ends:].mean(-1) - places[..., :ends].mean(-1)).norm(dim=-1)
    elapsed = times[:, -ends:].mean(-1) - times[:, :ends].mean(-1)
    advancing = elapsed > 0
    if not bool(advancing.any()):
        return math.nan
    return float((moved[advancing] / elapsed[advancing]).max())


def _compare_peaks(
    speeds: tuple[float, float], legs_m: tuple[float, float], s: MovementSettings
) -> tuple[tuple[float, float], str]:
    """The reference's and the student's peak Froude numbers from their peak ``speeds``
    (m/s, :func:`peak_speed`) and ``legs_m``, and the sentence saying that one runs somewhere
    while the other never leaves a walk ("" otherwise)."""
    froudes = (froude_number(speeds[0], legs_m[0]), froude_number(speeds[1], legs_m[1]))
    gaits = [
        "run" if f >= s.running_froude else "walk" if f < s.walking_froude else None
        for f in froudes
    ]
    if set(gaits) != {"walk", "run"}:
        return froudes, ""
    runner = 1 if gaits[1] == "run" else 0
    who = ("the reference", "the student")
    return froudes, (
        f"{who[runner]} runs for {s.min_compared_s:g} s at {speeds[runner]:.1f} m/s (Froude "
        f"number {froudes[runner]:.2f}) but {who[1 - runner]} never leaves a walk (at most "
        f"{speeds[1 - runner]:.1f} m/s, {froudes[1 - runner]:.2f}): people walk below "
        f"{s.walking_froude:g} and run from {s.running_froude:g}"
    )


def _compare_gaits(
    speeds: tuple[float, float], legs_m: tuple[float, float], s: MovementSettings
) -> tuple[tuple[float, float], str]:
    """The reference's and the student's Froude numbers from their ``speeds`` (m/s) and
    ``legs_m``, and the sentence saying that one walks and the other runs ("" otherwise)."""
    froudes = (froude_number(speeds[0], legs_m[0]), froude_number(speeds[1], legs_m[1]))
    gaits = [_gait(f, s) for f in froudes]
    if set(gaits) != {"walk", "run"}:
        return froudes, ""
    said = [
        f"{who} at {v:.1f} m/s (Froude number {f:.2f} for a {leg:.2f} m leg: "
        f"{'a walk' if gait == 'walk' else 'a run'})"
        for who, v, f, leg, gait in zip(
            ("the reference", "the student"), speeds, froudes, legs_m, gaits, strict=True
        )
    ]
    return froudes, (
        f"{said[1]} but {said[0]}: people walk below {s.walking_froude:g} and run from "
        f"{s.running_froude:g}"
    )


def _compare_paths(
    student: Tensor, reference: Tensor, window: int, s: MovementSettings
) -> tuple[tuple[float, float], str]:
    """The reference's and the student's path straightness (:func:`path_straightness` of
    ``(n, 3)`` positions over windows of ``window`` video frames), and the sentence saying
    that the student goes back and forth where the reference travels on ("" otherwise; both
    must cover at least ``travelling_m``, the reference net, the student along the path)."""
    ours, net, path = path_straightness(student, window)
    theirs, reference_net, _ = path_straightness(reference, window)
    # a student who hardly moves is the travel check's: the jitter of a root in place
    # makes no path
    moving = reference_net >= s.travelling_m and path >= s.travelling_m
    if not moving or ours >= s.min_straightness * theirs:
        return (theirs, ours), ""
    return (theirs, ours), (
        f"the student goes back and forth: {path:.1f} m of path for {net:.1f} m of net "
        f"travel ({ours:.2f} of it) where the reference travels {reference_net:.1f} m, "
        f"{theirs:.2f} of its path (the same movement goes at least {s.min_straightness:g} "
        "times as straight)"
    )


def _gait_check(
    c: Tensor,
    student: Tensor,
    reference: Tensor,
    rates: tuple[float, float],
    legs_m: tuple[float, float],
    s: MovementSettings,
    seen: slice,
) -> tuple[tuple[float, float], tuple[float, float], str]:
    """The gait check on the compared stretch (``c`` ``(n,)``, the student's root ``student``
    and the reference's at C ``reference``, ``(n, 3)`` float64 metres on the host): the reference's and the student's Froude numbers over the whole stretch and
    at their peaks (:func:`peak_speed`, over the ``seen`` frames only), and the sentence
    saying that one walks and the other runs ("" when neither comparison says so; the whole
    stretch's said first)."""
    reference_rate, video_rate = rates
    k = max(1, round(s.end_window_s * video_rate))
    n = c.shape[0]
    # each performer's net speed at their own clock: the mean positions over the end
    # windows lie (n - k) video frames apart for the student, and the reference frames C
    # matches to those windows apart for the reference
    froudes, reason = (math.nan, math.nan), ""
    reference_s = float(c[-k:].double().mean() - c[:k].double().mean()) / reference_rate
    if reference_s > 0:
        speeds = (
            net_displacement_m(reference, k) / reference_s,
            net_displacement_m(student, k) / ((n - k) / video_rate),
        )
        froudes, reason = _compare_gaits(speeds, legs_m, s)
    window = round(s.min_compared_s * video_rate)
    frames = torch.arange(n, dtype=torch.float64)[seen]
    peaks = (
        peak_speed(reference[seen], c[seen].double() / reference_rate, window, k),
        peak_speed(student[seen], frames / video_rate, window, k),
    )
    peak_froudes = (math.nan, math.nan)
    if not any(math.isnan(p) for p in peaks):
        peak_froudes, peak_reason = _compare_peaks(peaks, legs_m, s)
        reason = reason or peak_reason
    return froudes, peak_froudes, reason


def _seen_stretch(in_view: Tensor | None, core: slice, n: int) -> slice:
    """The frames of the compared stretch (``core`` of the video, ``n`` frames long) from its
    first to its last frame ``in_view`` (``(T',)`` bool; ``None``: all of it); an empty
    slice when none is."""
    if in_view is None:
        return slice(0, n)
    seen = in_view.to(torch.bool).cpu()[core].nonzero().flatten()
    if len(seen) == 0:
        return slice(0, 0)
    return slice(int(seen[0]), int(seen[-1]) + 1)


def check_movement(
    c: Tensor,
    translation: Tensor,
    reference_root: Tensor,
    reference_rate: float,
    video_rate: float,
    scale: float,
    settings: MovementSettings | None = None,
    legs_m: tuple[float, float] | None = None,
    in_view: Tensor | None = None,
) -> MovementCheck:
    """Decide whether the student performs the reference's movement (module docstring).

    Args:
        c: ``(T',)`` long, the registration's C.
        translation: ``(T', 3)`` the student root's positions, metres.
        reference_root: ``(T, 3)`` the reference root's positions, metres.
        reference_rate, video_rate: frames per second.
        scale: G.
        settings: :class:`MovementSettings` (defaults otherwise).
        legs_m: the reference's and the student's standing hip heights, metres
            (:func:`leg_length_m`; ``None``: the gait is not compared).
        in_view: ``(T',)`` bool, the video frames where the person is in some camera's
            image, not entering or leaving it (its silhouette off the left and right edges:
            :meth:`~motion.registration.types.VideoFeatures.within_sides`; ``None``: all).
            The path's straightness and the peak gait read the root only between the first
            and the last of them: half a body at the image's side has its depth placed
            poorly, and its root swings metres.

    Returns:
        :class:`MovementCheck`.
    """
    s = settings or MovementSettings()
    c = c.to(torch.long).cpu()
    if c.shape[0] < 2:
        return MovementCheck(True)
    start, end = held_ends(c)
    if start + end > s.max_held * c.shape[0] or c.shape[0] - start - end < 2:
        start, end = 0, 0  # not an end held: stalls
    full_length = c.shape[0]
    core = slice(start, full_length - end)
    c, translation = c[core], translation[core]
    n = c.shape[0]
    held = _held_warnings(start, end, video_rate, c, s.held_warning_s)
    steps = np.diff(c.numpy())
    slope = float(np.polyfit(np.arange(n, dtype=np.float64), c.numpy().astype(np.float64), 1)[0])
    speed = slope * video_rate / reference_rate
    k = max(1, round(s.end_window_s * video_rate))
    student_path = translation.detach().cpu().double()
    reference_path = reference_root.detach().cpu().double()[c]  # the reference's own size
    student = net_displacement_m(student_path, k)
    ref = net_displacement_m(reference_path, k) * scale
    reasons = []
    travelling = max(student, ref) >= s.travelling_m
    apart = abs(student - ref) > s.min_travel_difference_m
    ratio = student / max(ref, 1e-9)
    if travelling and apart and not 1 / s.max_travel_ratio <= ratio <= s.max_travel_ratio:
        times = f"{ratio:.2f} times as far" if ratio < 100 else "far more"
        reasons.append(
            f"the reference travels {ref:.1f} m over the matched stretch but the student "
            f"{student:.1f} m ({times}; the same movement stays within "
            f"{1 / s.max_travel_ratio:.2f}-{s.max_travel_ratio:.2f})"
        )
    stalled = None
    if slope >= s.stall_min_step:
        stalled = float((steps == 0).mean())
        if stalled > s.max_stalled:
            reasons.append(
                f"the matching reference moment stands still on {100 * stalled:.0f} % of the "
                f"video's frames (stop-and-go: no later reference posture fits; at most "
                f"{100 * s.max_stalled:.0f} % for the same movement)"
            )
    fast = float((steps >= s.fast_step_factor * reference_rate / video_rate).mean())
    if fast > s.max_fast:
        reasons.append(
            f"the matching reference moment races ahead at {s.fast_step_factor:g} times the "
            f"reference's pace or more on {100 * fast:.0f} % of the video's frames (at most "
            f"{100 * s.max_fast:.0f} % for the same movement)"
        )
    long_enough = (n - k) / video_rate >= s.min_compared_s
    if long_enough and speed < s.min_pace:
        reasons.append(
            f"the matching reference moment advances at {100 * speed:.0f} % of the "
            f"reference's pace: the student holds one of its postures rather than performing "
            f"the movement (at least {100 * s.min_pace:.0f} % for the same movement at "
            "another tempo)"
        )
    seen = _seen_stretch(in_view, core, n)
    seen_long_enough = (seen.stop - seen.start - k) / video_rate >= s.min_compared_s
    straightness = (math.nan, math.nan)
    window = max(1, round(s.path_window_s * video_rate))
    if seen_long_enough and (seen.stop - seen.start) // window >= 3:
        straightness, reason = _compare_paths(
            student_path[seen],
            reference_path[seen] * scale,
            window,
            s,
        )
        reasons += [reason] if reason else []
    froudes = peak_froudes = (math.nan, math.nan)
    if legs_m is not None and long_enough:
        froudes, peak_froudes, reason = _gait_check(
            c, student_path, reference_path, (reference_rate, video_rate), legs_m, s, seen
        )
        reasons += [reason] if reason else []
    short = []
    if not long_enough and not reasons:  # a match by default: say what was not checked
        short.append(
            f"the video lasts {n / video_rate:.2f} s where it matches the reference: too short "
            f"for the pace, the path and the gait checks, which need {s.min_compared_s:g} s "
            "(about one stride) between its ends, so whether the student performs the "
            "reference's movement is not known"
        )
    return MovementCheck(
        motions_match=not reasons,
        reasons=reasons,
        student_travel_m=student,
        reference_travel_m=ref,
        stalled_fraction=stalled,
        fast_fraction=fast,
        speed_ratio=speed,
        held_start=start,
        held_end=end,
        warnings=[*held, *short],
        student_froude=froudes[1],
        reference_froude=froudes[0],
        student_froude_peak=peak_froudes[1],
        reference_froude_peak=peak_froudes[0],
        student_straightness=straightness[1],
        reference_straightness=straightness[0],
    )
