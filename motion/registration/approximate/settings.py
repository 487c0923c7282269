"""Stage 1's settings: :class:`Stage1Settings`, every tuning constant of stage 0's body scale
and stage 1's approximate registration (checked when built), and :func:`_settings`, the check
of a ``settings`` argument (``None``: the defaults).

Units as :mod:`motion.registration.approximate` states them: metres, radians (degrees only in
names ending ``_deg``), pixels; cost distances in pixels over the body's pixel height ``h``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from motion.registration.types import RegistrationError


@dataclass(frozen=True)
class Stage1Settings:
    """Every tuning constant of stage 1.

    Starts and optimiser (per pair):
        yaw_starts: rotations tried per pair: the reference's up mapped onto the world's up
            (from the cameras), at this many yaw angles evenly spaced about it.
        refine_starts: the best screened starts refined by Levenberg-Marquardt (a warm start
            ``init``, and with keypoints the 2-D joint pose, are refined as well). The
            screening ranks starts by their cost before any refinement, which misleads where
            little of the body is in view: on the synthetic walk's last frames (body cut by
            two image edges) 2 of them missed the true ``T``'s basin at one frame in four, 4
            did not (stage 1 2.4 -> 3.0 s).
        iterations: LM iterations per refined start.
        anchor_stride: where a pair's reference frames are a run of neighbours (the bands of
            the time alignment), only every ``anchor_stride``-th is fitted from all starts; each
            pair is then refined from the best ``T`` of the two anchors around it for
            ``warm_iterations`` LM iterations (1: every pair from all starts). Columns count
            as neighbours when consecutive ones are at most ``anchor_gap`` frames apart.
        lm_damping: initial Marquardt damping (relative to the diagonal of ``J^T J``).
        final_yaw_starts, final_refine_starts, final_iterations: the same for the final fit of
            ``T`` per video frame at the chosen pair.
        final_edge_weight: ``edge_weight`` of that final fit. Edges help to rank reference
            frames (internal edges show which limb is where), but bias ``T``: outline points
            of capsule sides hidden inside the body, and Canny edges ~1 px off the contour,
            pull the fit (measured on a rendered pair: 7 degrees / 6 cm off with edges,
            1 degree / 1 cm with silhouettes alone).

    Cost (all distances in pixels over the body's pixel height ``h``; each term a mean):
        outside_weight: model interior points outside the silhouette.
        uncovered_weight: silhouette pixels no capsule covers.
        edge_weight: model outline points against observed edges (if ``edge_distance``).
        keypoint_weight: 2-D joints (if keypoints), Cauchy with scale ``keypoint_sigma * h``.
        truncate: silhouette distances are cut at ``truncate * h``.
        edge_truncate: edge distances are cut at ``edge_truncate * h``.
        observed_points: silhouette pixels subsampled per frame and camera (fixed per call).
        interior_along, interior_across, interior_cap: interior samples per part
            (:class:`motion.body.observation.SampleLayout`).
        outline_side, outline_arc: outline samples per side line and per end arc.
        depth_prior: weight (per metre^2, relative to a ray's perpendicular error) of the
            depth guessed from the silhouette's pixel height when the starts' position is
            triangulated from the silhouette centroids (alone decisive with one camera).
        clipped_depths: where a silhouette touches the image's top or bottom edge (the
            person partly out of view), its pixel height is only a lower bound of the body's,
            so the depth it gives is too far: starts are screened at each of these fractions
            of that depth, the body hung from the silhouette's edge that is in view. Model
            points outside the image cost nothing in any case (they are not observed). On
            the synthetic walk, one camera, whose feet leave the image in the last 30 % of
            the frames, the fits at the true pairs there were 2-4x the cost of the true ``T``
            and up to 105 degrees off without them.
        clipped_shifts: where a silhouette touches the image's left or right edge, its
            centroid lies short of the body's on the cut side: starts are also screened with
            the centroid moved toward that edge by each of these fractions of the
            silhouette's pixel height (the first one for every frame, as the depths).
        heading_weight: a prior, not an image term: people move the way the reference
            moves. Where the person travels (the track of root positions from rigid fits
            against ``yaw_starts`` evenly spaced reference frames, velocity over
            ``heading_window`` seconds; those fits count as pair evaluations) and the root
            moves (in its own frame, turned by the candidate's ``R``) both faster than
            ``heading_speed`` m/s, a candidate whose two horizontal directions differ by
            more than ``heading_tolerance_deg`` pays up to ``heading_weight`` (at 180 degrees;
            linear in the angle's cosine beyond the tolerance). It breaks the mirror ambiguity
            of silhouettes (the body turned 180 degrees with the legs swapped looks the same
            from the front), which otherwise lets a whole walk lock half a gait cycle off; 0
            disables it. It ranks starts and candidates, the LM fits the image cost alone.
        heading_tolerance_deg: the prior tells front from back, not the exact heading: a
            person turning, side-stepping or swaying moves up to tens of degrees away from
            where the reference's root moves. On the synthetic walk (turned 30 degrees over the
            video about its first position, so the path swings sideways) the true ``T`` was up
            to 45 degrees off the track; penalised from 0 degrees, that outweighed the image
            cost at the true pairs 2-5 times in the last third of the frames.
        reference_up, reference_forward: the reference's up and facing axes in ``B_t``
            (BVH: +Y up; the facing axis only orients yaw 0).

    Time alignment (:func:`motion.alignment.coarse_to_fine_align`):
        step_factor: ``max_step = ceil(step_factor * reference.frame_rate / video.frame_rate)``.
        factor, radius, max_cells: coarse-to-fine subsampling factor, band half-width in
            reference frames (``None``: ``max_step + factor``), cells solved directly.
        beam, prune: the finest levels' tracking of the best partial paths: half-width in
            reference frames (``None``: ``radius``; 0: no tracking) and how close (threshold
            units) the next best path must be to keep a beam of its own (0: none). On the
            synthetic walk with one camera, ``prune=1`` found lower-cost paths further from
            the truth (stage 1's C 9.7 vs 6.6 reference frames, 30 % more pairs).
        robust, robust_scale: truncation of pair costs at ``robust_scale`` x the median row
            minimum, so a bad stretch cannot pull the path.
        slope_weight: quadratic slope prior around the frame-rate ratio (threshold units).
        fix_start, fix_end: force ``C(0) = 0`` / ``C(T'-1) = T-1``.

    Temporal consistency of the final ``T``:
        smooth_weight: cost (in pair-cost units) of ``angle^2 + (|dp| / body height)^2``
            (radians, metres) between neighbouring video frames, minimised exactly over each
            frame's candidates (chain Viterbi).
        smooth_rounds: rounds of re-fitting every frame warm-started from its neighbours'
            chosen ``T``, each followed by the Viterbi.

    Body scale (:func:`estimate_body_scale`):
        scale_reference_frames: reference frames (evenly spaced) tried per video frame.
        scale_iterations: LM iterations of the fit with the scale free.
        scale_rounds: fits with the scale free, each at the previous estimate.
        scale_observed_points, scale_edge_weight: ``observed_points`` and ``edge_weight``
            of those fits. Size is read from silhouette coverage, which needs more samples
            than ranking pairs; and edges pull a free-scale fit small (outline points of
            capsule sides hidden inside the body are drawn to nearby edges): measured on the
            synthetic walk at G = 1.1 from two cameras, -2 to -4 % with the pair settings,
            -0.5 to -1.5 % with these.

    Memory and numbers:
        chunk: problems (pairs x starts) per batched step; memory ~ chunk x 60 kB per camera.
        dtype: of all computation and results.
    """

    yaw_starts: int = 8
    refine_starts: int = 4
    iterations: int = 8
    anchor_stride: int = 4
    anchor_gap: int = 8
    warm_iterations: int = 4
    lm_damping: float = 1e-2
    final_yaw_starts: int = 16
    final_refine_starts: int = 4
    final_iterations: int = 20
    final_edge_weight: float = 0.0
    outside_weight: float = 1.0
    uncovered_weight: float = 1.0
    edge_weight: float = 0.2
    keypoint_weight: float = 1.0
    keypoint_sigma: float = 0.05
    truncate: float = 0.3
    edge_truncate: float = 0.05
    observed_points: int = 48
    interior_along: int = 2
    interior_across: int = 2
    interior_cap: int = 2
    outline_side: int = 2
    outline_arc: int = 2
    depth_prior: float = 0.05
    clipped_depths: tuple[float, ...] = (1.0, 0.85, 0.7, 0.55)
    clipped_shifts: tuple[float, ...] = (0.0, 0.1, 0.2)
    heading_weight: float = 2e-3
    heading_speed: float = 0.3
    heading_window: float = 0.5
    heading_tolerance_deg: float = 60.0
    reference_up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    reference_forward: tuple[float, float, float] = (0.0, 0.0, 1.0)
    step_factor: float = 2.0
    factor: int = 4
    radius: int | None = None
    max_cells: int = 2000
    beam: int | None = None
    prune: float = 0.0
    robust: str = "truncate"
    robust_scale: float = 2.0
    slope_weight: float = 0.02
    fix_start: bool = False
    fix_end: bool = False
    smooth_weight: float = 2e-3
    smooth_rounds: int = 2
    scale_reference_frames: int = 64
    scale_iterations: int = 20
    scale_rounds: int = 2
    scale_observed_points: int = 128
    scale_edge_weight: float = 0.0
    chunk: int = 1024
    dtype: torch.dtype = torch.float32

    def __post_init__(self):
        positive = (
            "yaw_starts refine_starts iterations anchor_stride anchor_gap warm_iterations "
            "final_yaw_starts final_refine_starts "
            "final_iterations observed_points interior_along interior_across interior_cap "
            "outline_side scale_rounds scale_observed_points "
            "factor max_cells scale_reference_frames scale_iterations chunk"
        ).split()
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in positive and (
                isinstance(value, bool) or not isinstance(value, int) or value < 1
            ):
                raise RegistrationError(
                    f"Stage1Settings.{f.name} must be an int >= 1; got {value!r}"
                )
            if isinstance(f.default, float) and (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not (math.isfinite(value) and value >= 0)
            ):
                raise RegistrationError(
                    f"Stage1Settings.{f.name} must be a finite number >= 0; got {value!r}"
                )
        if self.refine_starts > self.yaw_starts or self.final_refine_starts > self.final_yaw_starts:
            raise RegistrationError(
                "Stage1Settings: refine_starts must be <= yaw_starts (and final_refine_starts <= "
                f"final_yaw_starts); got {self.refine_starts}/{self.yaw_starts} and "
                f"{self.final_refine_starts}/{self.final_yaw_starts}"
            )
        for name in ("outline_arc", "smooth_rounds"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise RegistrationError(f"Stage1Settings.{name} must be an int >= 0; got {value!r}")
        for name, least in (("radius", 1), ("beam", 0)):
            value = getattr(self, name)
            if value is not None and (
                isinstance(value, bool) or not isinstance(value, int) or value < least
            ):
                raise RegistrationError(
                    f"Stage1Settings.{name} must be None or an int >= {least}; got {value!r}"
                )
        for name in ("fix_start", "fix_end"):
            if not isinstance(getattr(self, name), bool):
                raise RegistrationError(
                    f"Stage1Settings.{name} must be True or False; got {getattr(self, name)!r}"
                )
        if self.factor < 2:
            raise RegistrationError(f"Stage1Settings.factor must be >= 2; got {self.factor}")
        if not self.heading_tolerance_deg < 180:
            raise RegistrationError(
                "Stage1Settings.heading_tolerance_deg must be in [0, 180); got "
                f"{self.heading_tolerance_deg!r}"
            )
        depths = self.clipped_depths
        if not (
            isinstance(depths, tuple)
            and depths
            and all(isinstance(f, int | float) and 0 < f <= 1 for f in depths)
        ):
            raise RegistrationError(
                "Stage1Settings.clipped_depths must be a non-empty tuple of fractions in (0, 1]; "
                f"got {depths!r}"
            )
        shifts = self.clipped_shifts
        if not (
            isinstance(shifts, tuple)
            and shifts
            and all(isinstance(f, int | float) and 0 <= f < 1 for f in shifts)
        ):
            raise RegistrationError(
                "Stage1Settings.clipped_shifts must be a non-empty tuple of fractions in [0, 1); "
                f"got {shifts!r}"
            )
        if self.robust not in ("truncate", "saturate"):
            raise RegistrationError(
                f"Stage1Settings.robust must be 'truncate' or 'saturate'; got {self.robust!r}"
            )
        for name in (
            "truncate",
            "edge_truncate",
            "keypoint_sigma",
            "robust_scale",
            "step_factor",
            "heading_speed",
            "heading_window",
        ):
            if not getattr(self, name) > 0:
                raise RegistrationError(
                    f"Stage1Settings.{name} must be > 0; got {getattr(self, name)!r}"
                )
        for name in ("reference_up", "reference_forward"):
            v = getattr(self, name)
            if len(v) != 3 or not math.isfinite(sum(v)) or sum(x * x for x in v) < 1e-12:
                raise RegistrationError(
                    f"Stage1Settings.{name} must be a non-zero 3-vector; got {v!r}"
                )
        if self.dtype not in (torch.float32, torch.float64):
            raise RegistrationError(
                f"Stage1Settings.dtype must be torch.float32 or torch.float64; got {self.dtype}"
            )


def _settings(settings: Stage1Settings | None) -> Stage1Settings:
    if settings is None:
        return Stage1Settings()
    if not isinstance(settings, Stage1Settings):
        raise RegistrationError(
            f"settings must be Stage1Settings or None; got {type(settings).__name__}"
        )
    return settings
