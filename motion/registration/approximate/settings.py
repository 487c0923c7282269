"""Stage 1's settings: :class:`Stage1Settings`, every tuning constant of stage 0's body scale
and stage 1's approximate registration (each field with its range and meaning,
:func:`motion.settings.setting`; checked when built), and :func:`_settings`, the check of a
``settings`` argument (``None``: the defaults).

Units as :mod:`motion.registration.approximate` states them: metres, radians (degrees only in
names ending ``_deg``), pixels; cost distances in pixels over the body's pixel height ``h``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from motion.registration.types import RegistrationError
from motion.settings import SettingError, Settings, setting, show


class Stage1SettingsError(SettingError, RegistrationError):
    """A stage-1 setting outside its type or range (a :class:`RegistrationError` too)."""


@dataclass(frozen=True)
class Stage1Settings(Settings):
    """Every tuning constant of stage 1 (and of stage 0's body scale). Every field is checked
    at construction (a bad value raises :class:`Stage1SettingsError` naming it, what it
    must be and what it got); ``python -m motion register --write-config`` writes each with
    its meaning.

    The fields in order: the starts and optimiser of each (video frame, reference frame)
    pair; the final fit of ``T`` per video frame; the cost (all distances in pixels over the
    body's pixel height ``h``, each term a mean); the heading prior; the time alignment
    (:func:`motion.alignment.coarse_to_fine_align`); the temporal consistency of the final
    ``T``; the body scale (:func:`~motion.registration.approximate.estimate_body_scale`);
    memory and numbers. Checked together: ``refine_starts <= yaw_starts``,
    ``final_refine_starts <= final_yaw_starts``, and ``reference_up`` and
    ``reference_forward`` are not zero.
    """

    setting_error: ClassVar[type[SettingError]] = Stage1SettingsError

    # -- starts and optimiser (per pair)
    yaw_starts: int = setting(
        8,
        "rotations tried per pair: the reference's up mapped onto the world's up (from the "
        "cameras), at this many yaw angles evenly spaced about it",
        ge=1,
    )
    refine_starts: int = setting(
        4,
        "the best screened starts refined by Levenberg-Marquardt (a warm start, and with "
        "keypoints the 2-D joint pose, are refined as well); the screening ranks starts by "
        "their cost before any refinement, which misleads where little of the body is in view",
        ge=1,
    )
    iterations: int = setting(8, "Levenberg-Marquardt iterations per refined start", ge=1)
    anchor_stride: int = setting(
        4,
        "where a pair's reference frames are a run of neighbours (the bands of the time "
        "alignment), only every anchor_stride-th is fitted from all starts; each pair is then "
        "refined from the best T of the two anchors around it (1: every pair from all starts)",
        ge=1,
    )
    anchor_gap: int = setting(
        8,
        "reference frames count as neighbours (for anchor_stride) when consecutive ones are "
        "at most this many frames apart",
        ge=1,
    )
    warm_iterations: int = setting(
        4,
        "Levenberg-Marquardt iterations of a pair refined from its anchors' T",
        ge=1,
    )
    lm_damping: float = setting(
        1e-2, "initial Marquardt damping (relative to the diagonal of J^T J)", ge=0
    )
    # -- the final fit of T per video frame at the chosen pair
    final_yaw_starts: int = setting(16, "yaw_starts of the final fit of T per video frame", ge=1)
    final_refine_starts: int = setting(
        4, "refine_starts of the final fit of T per video frame", ge=1
    )
    final_iterations: int = setting(20, "iterations of the final fit of T per video frame", ge=1)
    final_edge_weight: float = setting(
        0.0,
        "edge_weight of the final fit: edges help to rank reference frames (internal edges "
        "show which limb is where) but bias T, as outline points of capsule sides hidden "
        "inside the body and Canny edges about 1 px off the contour pull the fit",
        ge=0,
    )
    # -- the cost (distances in pixels over the body's pixel height h; each term a mean)
    outside_weight: float = setting(
        1.0,
        "weight of the model's interior points outside the silhouette (cost distances are in "
        "pixels over the body's pixel height h; each term is a mean)",
        ge=0,
    )
    uncovered_weight: float = setting(
        1.0, "weight of the silhouette pixels no capsule covers", ge=0
    )
    edge_weight: float = setting(
        0.2,
        "weight of the model's outline points against the observed edges (where the video "
        "gives edges)",
        ge=0,
    )
    keypoint_weight: float = setting(
        1.0,
        "weight of the 2-D joints (where keypoints are given), a Cauchy loss of scale "
        "keypoint_sigma * h",
        ge=0,
    )
    keypoint_sigma: float = setting(
        0.05, "scale of the 2-D joints' Cauchy loss, as a fraction of h", gt=0
    )
    truncate: float = setting(0.3, "silhouette distances are cut at truncate * h", gt=0)
    edge_truncate: float = setting(0.05, "edge distances are cut at edge_truncate * h", gt=0)
    observed_points: int = setting(
        48, "silhouette pixels subsampled per frame and camera (fixed per call)", ge=1
    )
    interior_along: int = setting(
        2, "interior samples per part along its axis (motion.body.observation.SampleLayout)", ge=1
    )
    interior_across: int = setting(2, "interior samples per part across its axis", ge=1)
    interior_cap: int = setting(2, "interior samples per part in each end cap", ge=1)
    outline_side: int = setting(2, "outline samples per side line of a part", ge=1)
    outline_arc: int = setting(2, "outline samples per end arc of a part", ge=0)
    depth_prior: float = setting(
        0.05,
        "weight (per metre^2, relative to a ray's perpendicular error) of the depth guessed "
        "from the silhouette's pixel height when the starts' position is triangulated from "
        "the silhouette centroids (alone decisive with one camera)",
        ge=0,
    )
    clipped_depths: tuple[float, ...] = setting(
        (1.0, 0.85, 0.7, 0.55),
        "where a silhouette touches the image's top or bottom edge (the person partly out of "
        "view), its pixel height is only a lower bound of the body's, so the depth it gives is "
        "too far: starts are screened at each of these fractions of that depth, the body hung "
        "from the silhouette's edge that is in view (model points outside the image cost "
        "nothing in any case)",
        gt=0,
        le=1,
        min_length=1,
    )
    clipped_shifts: tuple[float, ...] = setting(
        (0.0, 0.1, 0.2),
        "where a silhouette touches the image's left or right edge, its centroid lies short of "
        "the body's on the cut side: starts are also screened with the centroid moved toward "
        "that edge by each of these fractions of the silhouette's pixel height (the first one "
        "for every frame, as the depths)",
        ge=0,
        lt=1,
        min_length=1,
    )
    # -- the heading prior
    heading_weight: float = setting(
        2e-3,
        "a prior, not an image term: people move the way the reference moves. Where the "
        "person travels (the track of root positions from rigid fits against yaw_starts "
        "evenly spaced reference frames, velocity over heading_window) and the reference's "
        "root moves (turned by the candidate's R) both faster than heading_speed, a "
        "candidate whose two horizontal directions differ by more than heading_tolerance_deg "
        "pays up to this (at 180 degrees; linear in the angle's cosine beyond the tolerance). "
        "It breaks the mirror ambiguity of silhouettes (the body turned 180 degrees with the "
        "legs swapped looks the same from the front), which otherwise lets a whole walk lock "
        "half a gait cycle off; it ranks starts and candidates, the fits use the image cost "
        "alone; 0 disables it",
        ge=0,
    )
    heading_speed: float = setting(
        0.3,
        "metres per second the person and the reference's root must both exceed for the "
        "heading prior to apply",
        gt=0,
    )
    heading_window: float = setting(
        0.5, "seconds over which the heading prior's velocities are taken", gt=0
    )
    heading_tolerance_deg: float = setting(
        60.0,
        "degrees the two headings may differ unpenalised: the prior tells front from back, "
        "not the exact heading (a person turning, side-stepping or swaying moves up to tens "
        "of degrees away from where the reference's root moves)",
        ge=0,
        lt=180,
    )
    reference_up: tuple[float, float, float] = setting(
        (0.0, 1.0, 0.0), "the reference's up axis in its own frame (BVH: +Y up)"
    )
    reference_forward: tuple[float, float, float] = setting(
        (0.0, 0.0, 1.0), "the reference's facing axis in its own frame (it orients yaw 0 only)"
    )
    # -- the time alignment (motion.alignment.coarse_to_fine_align)
    step_factor: float = setting(
        2.0,
        "the path's largest step in reference frames per video frame is step_factor times "
        "the reference's frame rate over the video's (rounded up)",
        gt=0,
    )
    factor: int = setting(4, "coarse-to-fine subsampling factor", ge=2)
    radius: int | None = setting(
        None,
        "half-width in reference frames of the band refined at each finer level (none: the "
        "largest step + factor)",
        ge=1,
    )
    max_cells: int = setting(
        2000, "cost-matrix cells solved directly, without a coarser level", ge=1
    )
    beam: int | None = setting(
        None,
        "the finest levels' tracking of the best partial paths: its half-width in reference "
        "frames (none: radius; 0: no tracking)",
        ge=0,
    )
    prune: float = setting(
        0.0,
        "how close (threshold units) the next best path must be to keep a beam of its own "
        "(0: none)",
        ge=0,
    )
    robust: str = setting(
        "truncate",
        "how pair costs are capped at robust_scale times the median row minimum, so that a "
        "bad stretch cannot pull the path: truncate or saturate",
        choices=("truncate", "saturate"),
    )
    robust_scale: float = setting(
        2.0, "pair costs are capped at this times the median row minimum", gt=0
    )
    slope_weight: float = setting(
        0.02,
        "quadratic slope prior around the frame-rate ratio (threshold units: a pair's cost is "
        "capped at 1). Stronger, it keeps a time-warped copy of the reference and a long walk "
        "in phase, but pulls another performer's tempo toward the ratio and moves stage 1's "
        "failures on other performers rather than removing them: 0.1 measured against it in "
        "docs/results/stage1_draws.md",
        ge=0,
    )
    tempo_weight: float = setting(
        0.0,
        "a second pass of the time alignment with a slope prior of this weight (threshold "
        "units) around the student's tempo fitted to the first pass's C "
        "(motion.registration.approximate.registration.fitted_tempo) instead of the "
        "frame-rate ratio: against stalls that drop a cycle without pulling another "
        "performer's steady tempo toward the reference's. Measured on other performers it "
        "moves stage 1's failures as a stronger slope_weight does (docs/experiments.md, "
        '"Stage 1\'s C across seeds"); 0: one pass',
        ge=0,
    )
    fix_start: bool = setting(False, "force C(0) = 0 (the first frames match)")
    fix_end: bool = setting(False, "force C(T'-1) = T-1 (the last frames match)")
    # -- temporal consistency of the final T
    smooth_weight: float = setting(
        2e-3,
        "cost (in pair-cost units) of angle^2 + (|dp| / body height)^2 (radians, metres) "
        "between neighbouring video frames' T, minimised exactly over each frame's candidates "
        "(chain Viterbi)",
        ge=0,
    )
    smooth_rounds: int = setting(
        2,
        "rounds of re-fitting every frame warm-started from its neighbours' chosen T, each "
        "followed by the Viterbi",
        ge=0,
    )
    # -- the body scale (stage 0)
    scale_reference_frames: int = setting(
        64, "reference frames (evenly spaced) tried per video frame", ge=1
    )
    scale_iterations: int = setting(
        20, "Levenberg-Marquardt iterations of the fit with the scale free", ge=1
    )
    scale_rounds: int = setting(2, "fits with the scale free, each at the previous estimate", ge=1)
    scale_observed_points: int = setting(
        128,
        "observed_points of the scale fits: size is read from silhouette coverage, which "
        "needs more samples than ranking pairs",
        ge=1,
    )
    scale_edge_weight: float = setting(
        0.0,
        "edge_weight of the scale fits: edges pull a free-scale fit small (outline points of "
        "capsule sides hidden inside the body are drawn to nearby edges)",
        ge=0,
    )
    # -- memory and numbers
    chunk: int = setting(
        1024,
        "problems (pairs x starts) per batched step; memory grows with it (about 60 kB per "
        "problem and camera)",
        ge=1,
    )
    dtype: torch.dtype = setting(
        torch.float32,
        "of all computation and results",
        choices=(torch.float32, torch.float64),
    )

    def validate(self) -> None:
        """Check (and normalise) every field, then the checks across fields (see the class
        docstring)."""
        super().validate()
        name = type(self).__name__
        for more, most in (
            ("refine_starts", "yaw_starts"),
            ("final_refine_starts", "final_yaw_starts"),
        ):
            if getattr(self, more) > getattr(self, most):
                raise Stage1SettingsError(
                    f"{name}: {more} must be <= {most} ({getattr(self, most)}); got "
                    f"{getattr(self, more)}"
                )
        for axis in ("reference_up", "reference_forward"):
            v = getattr(self, axis)
            if sum(x * x for x in v) < 1e-12:
                raise Stage1SettingsError(
                    f"{name}: {axis} must be a non-zero 3-vector; got {show(v)}"
                )


def _settings(settings: Stage1Settings | None) -> Stage1Settings:
    if settings is None:
        return Stage1Settings()
    if not isinstance(settings, Stage1Settings):
        raise RegistrationError(
            f"settings must be Stage1Settings or None; got {type(settings).__name__}"
        )
    return settings
