"""Stage 1, approximate registration (the proposal's problem "variation 1", Sections 4.4.2, 6.1).

For candidate pairs (video frame ``t'``, reference frame ``t``) find the best global rigid
transform ``T`` of the reference posture ``B_t`` (scaled by ``G``) against what the cameras saw
at ``t'``, from several starts; then the monotone correspondence ``C`` by the coarse-to-fine
chain aligner (:func:`motion.alignment.coarse_to_fine_align`) on those minimum costs, so that
long inputs never evaluate all ``T' x T`` pairs; then ``T`` per video frame at the chosen pair,
made consistent over time. Also the body-size estimate ``G`` where it is observable.

The image cost of a pair, summed over cameras (each term a mean over its points, distances in
pixels divided by the body's height in pixels ``h``, so costs compare across frames):

* silhouette, model -> image: interior sample points of the projected capsules against the
  distance transform of the silhouette's complement (0 inside the silhouette);
* silhouette, image -> model: a fixed random subsample of silhouette pixels against their
  distance to the nearest projected capsule (0 when covered);
* edges (when ``edge_distance`` is given): capsule outline points against the distance to the
  nearest observed edge, truncated (chamfer);
* 2-D joints (when keypoints are given): Cauchy-robust reprojection error, confidence weighted.

Silhouette distances are truncated at ``truncate * h`` (a far-off limb costs a bounded amount).
The 6 pose parameters (rotation increment left-multiplied about the root, translation; plus
log-scale for :func:`estimate_body_scale`) are refined by Levenberg-Marquardt with analytic
Jacobians (the capsules' image radii held fixed within a step), batched over all pairs x
starts of a chunk, in a batch-last layout (:class:`_Batch`).

Starts: the reference's up on the world's up (from the cameras) at several yaws, centred on
the triangulated silhouette centroid, screened by their cost; the best few are refined. In a
band of neighbouring reference frames only every ``anchor_stride``-th pair gets all starts,
the others are refined from the anchors around them (their best ``T`` differ little).

Candidates (starts and refined fits) are ranked by the image cost plus a heading prior
(``Stage1Settings.heading_weight``): a walker's silhouette seen from the front is nearly the
same turned 180 degrees with the legs swapped (half a gait cycle later), and without the
prior a whole sequence can lock onto that mirror branch; the prior asks that the person moves
in the direction the reference's root moves, turned by the candidate's rotation, to within
``Stage1Settings.heading_tolerance_deg`` (it tells front from back, not the exact heading).
Model points outside an image cost nothing: they are not observed.

Conventions (see :mod:`motion.registration.types`): ``T`` is the student's root joint transform
in the cameras' world frame, student joints ``= R (G B_t) + p``; metres, radians, pixels with
centres at integer ``(u, v)``, ``u`` right, ``v`` down; camera frames as OpenCV (x right, y down,
z forward); rotation matrices act on column vectors. Shapes: ``R`` rows (video frames of the
pairs), ``W`` reference frames per row, ``T'`` video frames, ``T`` reference frames, ``C``
cameras, ``P`` parts, ``S`` starts.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from motion.alignment import AlignmentError, coarse_to_fine_align, slope_step_cost
from motion.body.observation import SampleLayout
from motion.features import distance_to_edges
from motion.geometry import relative_angle, rotation_vector_to_matrix
from motion.pose import solve_pose, solve_pose_views
from motion.registration.types import (
    FRAME_CHUNK,
    Reference,
    RegistrationError,
    VideoFeatures,
    scaled_spec,
)
from pgm import TableFactor, chain_map

__all__ = [
    "PairFit",
    "Stage1Result",
    "Stage1Settings",
    "approximate_registration",
    "estimate_body_scale",
    "fit_rigid_pairs",
    "pair_costs",
]

Init = tuple[Tensor, Tensor]


#: how the note of :func:`estimate_body_scale` starts when G could not be estimated
SCALE_NOT_ESTIMATED = "G = 1.0 (not estimated)"


# -- settings and results ----------------------------------------------------------------------
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


@dataclass
class PairFit:
    """The best rigid transform of each pair (settings dtype).

    Attributes:
        cost: ``(R, W)`` cost at the best ``T``: the image cost (sum over cameras of mean
            squared height-relative distances; 0 is a perfect fit) plus the heading prior
            (``Stage1Settings.heading_weight``; :func:`pair_costs` gives the image cost of
            any ``T``).
        rotation: ``(R, W, 3, 3)`` the student root's world rotation.
        translation: ``(R, W, 3)`` the student root's world position, metres.
    """

    cost: Tensor
    rotation: Tensor
    translation: Tensor


@dataclass
class Stage1Result:
    """Approximate registration of a video (settings dtype).

    Attributes:
        C: ``(T',)`` long, reference frame of each video frame (monotone).
        rotation: ``(T', 3, 3)`` and translation ``(T', 3)`` (metres): ``T`` per video frame.
        cost: ``(T',)`` cost (as :attr:`PairFit.cost`, with ``final_edge_weight``) of each
            frame at ``(t', C(t'))`` and its ``T``.
        pair_evaluations: pair fits computed: the time alignment's (coarse level and
            bands), the heading track's and the final fits of ``T``.
        seconds: wall time.
    """

    C: Tensor
    rotation: Tensor
    translation: Tensor
    cost: Tensor
    pair_evaluations: int
    seconds: float


# -- small geometry helpers ----------------------------------------------------------------
def _unit(v) -> Tensor:
    v = torch.as_tensor(v, dtype=torch.float64)
    return v / v.norm()


# -- what is fixed during a call: the video's maps and the reference's geometry ---------------
@dataclass
class _Scene:
    """Precomputed inputs of the pair fits (settings dtype).

    Attributes:
        dout: distance (px) to the nearest silhouette pixel (0 inside) as a paired map
            (:func:`_pair_map`, ``T' C H W`` entries).
        edist: the same for the distance to the nearest observed edge (or ``None``).
        obs: ``(T', C, M, 2)`` subsampled silhouette pixels; obs_w ``(T', C, M)`` weights
            (summing to 1 per valid image, 0 for padding).
        height: ``(T', C)`` silhouette pixel height; cam_w ``(T', C)`` 1 where the camera
            sees a silhouette; centroid ``(T', C, 2)`` silhouette centroid (px); top_v,
            bottom_v ``(T', C)`` its first and last rows; clipped ``(T', C, 2)`` bool, it
            touches the image's top / bottom edge; side_clipped ``(T', C, 2)`` the left /
            right edge.
        keypoints: ``(T', C, K, 3)`` or ``None``; kp_joints ``(K,)`` long skeleton joints.
        landmarks: ``(T, P, 2, 3)`` capsule ends of ``B_t`` at scale G (metres);
            radii ``(P, 2)`` metres; joints ``(T, J, 3)``.
        centre_b: ``(T, 3)`` body centroid in ``B_t``; extent_b ``(T,)`` height along up;
            centre_from_top ``(T,)`` the centroid's depth below the body's top, a fraction
            of extent_b.
        K, R, t: ``(C, 3, 3)``, ``(C, 3, 3)``, ``(C, 3)`` cameras; orthographic; H, W.
        up, forward: ``(3,)`` world up (from the cameras) and yaw-0 facing direction.
        video_rate: Hz. track: ``(T', 3)`` the person's root position per video frame from
            rigid fits (NaN until needed, :func:`_track_at`); v_ref ``(T, 3)`` the reference
            root's velocity in its own frame (m/s), ``None`` without the heading prior.
        fits: pair fits so far (for :attr:`Stage1Result.pair_evaluations`); tracking: True
            while the track itself is being fitted (the heading prior is off then).
        settings: the call's :class:`Stage1Settings`; body_height: median height of ``B_t``
            along its up, metres (scales the translation smoothing).
        align: ``(3, 3)`` maps the reference's up/forward onto up/forward.
        interior, outline: canonical sample layouts, 6 rows each
            (:meth:`motion.body.observation.SampleLayout.canonical`), and their blends
            ``(3, S)`` (``(1-s)^2, (1-s) s, s^2``) and ``(2, S)`` (``1-s, s``); rows are
            stored as ``(S, 1)`` columns (the batch-last layout of :class:`_Batch`).
    """

    dout: Tensor
    edist: Tensor | None
    obs: Tensor
    obs_w: Tensor
    height: Tensor
    cam_w: Tensor
    centroid: Tensor
    top_v: Tensor
    bottom_v: Tensor
    clipped: Tensor
    side_clipped: Tensor
    keypoints: Tensor | None
    kp_joints: Tensor | None
    landmarks: Tensor
    radii: Tensor
    joints: Tensor
    centre_b: Tensor
    extent_b: Tensor
    centre_from_top: Tensor
    K: Tensor
    R: Tensor
    t: Tensor
    orthographic: bool
    H: int
    W: int
    up: Tensor
    forward: Tensor
    align: Tensor
    interior: tuple[Tensor, ...]
    outline: tuple[Tensor, ...]
    interior_blend: tuple[Tensor, Tensor]
    outline_blend: tuple[Tensor, Tensor]
    settings: Stage1Settings
    body_height: float
    video_rate: float = 1.0
    track: Tensor | None = None
    v_ref: Tensor | None = None
    fits: int = 0
    tracking: bool = False

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    @property
    def num_video(self) -> int:
        return self.obs.shape[0]

    @property
    def num_ref(self) -> int:
        return self.landmarks.shape[0]


def _pair_map(maps: Tensor) -> Tensor:
    """A map ``(..., H, W)`` as one flat entry per pixel holding its value and its right
    neighbour's (the last column repeats itself), viewed as one wider number so that one
    gather reads both: float32 pairs as float64, float64 pairs as complex128."""
    right = torch.cat([maps[..., 1:], maps[..., -1:]], -1)
    pairs = torch.stack([maps, right], -1).reshape(-1, 2).contiguous()
    wide = torch.float64 if maps.dtype == torch.float32 else torch.complex128
    return pairs.view(wide).reshape(-1)


def _pair_maps(make: Callable[[slice], Tensor], frames: int) -> Tensor:
    """:func:`_pair_map` of ``(T', C, H, W)`` maps built ``FRAME_CHUNK`` frames at a time by
    ``make(frames slice) -> (n, C, H, W)`` (settings dtype) into one flat tensor: the same
    entries as ``_pair_map`` of all frames (its order is frame-major), without ever holding
    more than a chunk's intermediates."""
    out = None
    for lo in range(0, frames, FRAME_CHUNK):
        part = _pair_map(make(slice(lo, min(lo + FRAME_CHUNK, frames))))
        if out is None:
            per_frame = part.numel() // min(FRAME_CHUNK, frames)
            out = torch.empty(frames * per_frame, dtype=part.dtype)
        out[lo * per_frame : lo * per_frame + part.numel()] = part
    return out


def _check_inputs(reference: Reference, video: VideoFeatures, scale: float) -> None:
    if not isinstance(reference, Reference):
        raise RegistrationError(f"expected a Reference; got {type(reference).__name__}")
    if not isinstance(video, VideoFeatures):
        raise RegistrationError(f"expected VideoFeatures; got {type(video).__name__}")
    if (
        isinstance(scale, bool)
        or not isinstance(scale, int | float)
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise RegistrationError(f"scale (G) must be a finite number > 0; got {scale!r}")
    sil = video.observation.silhouette
    _, tv, _c, h, w = sil.shape
    if tv == 0:
        raise RegistrationError(f"{video.name}: expected at least one video frame; got 0")
    if reference.num_frames == 0:
        raise RegistrationError(f"{reference.name}: expected at least one reference frame; got 0")
    if h < 2 or w < 2:
        raise RegistrationError(f"{video.name}: expected images of at least 2 x 2; got {w} x {h}")
    if not torch.isfinite(sil).all() or sil.min() < 0 or sil.max() > 1:
        raise RegistrationError(f"{video.name}: silhouettes must be finite and in [0, 1]")
    size = video.cameras.size.to(torch.float64)
    if size.shape != (_c, 2) or (size != torch.tensor([w, h], dtype=torch.float64)).any():
        raise RegistrationError(
            f"{video.name}: camera image sizes {size.tolist()} do not match the {w} x {h} "
            "silhouettes"
        )


def _build_scene(
    reference: Reference,
    video: VideoFeatures,
    scale: float,
    settings: Stage1Settings,
    generator: torch.Generator,
) -> _Scene:
    """Check the inputs and precompute what every pair fit reads (:class:`_Scene`): the
    distance maps, the silhouette subsample (drawn from ``generator``), the reference's
    capsules at scale ``scale`` for every frame, the world's up from the cameras."""
    _check_inputs(reference, video, scale)
    dt = settings.dtype
    obs = video.observation
    sil = obs.silhouette[0].to(dt)  # (T', C, H, W)
    tv, c, h, w = sil.shape
    mask = sil > 0.5
    count = mask.sum((-1, -2))  # (T', C)
    empty = (count == 0).all(1)
    if empty.any():
        frames = empty.nonzero().flatten()[:5].tolist()
        raise RegistrationError(
            f"{video.name}: expected a silhouette in at least one camera of every frame; "
            f"{int(empty.sum())} frames have none (first: {frames})"
        )
    cam_w = (count > 0).to(dt)
    # silhouette statistics for the starts and the normalisation, and the reference's
    # geometry, before the distance maps: their intermediates (float maps of every frame,
    # forward kinematics of every reference frame) then never sit on top of those maps
    rows_any = mask.any(-1)  # (T', C, H)
    vv = torch.arange(h, dtype=dt)
    top_v = torch.where(rows_any, vv, torch.full_like(vv, float(h))).amin(-1)
    bottom_v = torch.where(rows_any, vv, torch.full_like(vv, -1.0)).amax(-1)
    height = (bottom_v - top_v + 1).clamp_min(8.0)
    weight = sil * mask
    total = weight.sum((-1, -2)).clamp_min(1e-9)
    uu = torch.arange(w, dtype=dt)
    centroid = torch.stack(
        [(weight.sum(-2) * uu).sum(-1) / total, (weight.sum(-1) * vv).sum(-1) / total], -1
    )
    clipped = torch.stack([mask[..., 0, :].any(-1), mask[..., -1, :].any(-1)], -1)
    side_clipped = torch.stack([mask[..., :, 0].any(-1), mask[..., :, -1].any(-1)], -1)
    del weight, rows_any
    # the reference's geometry at scale G, every frame
    frames = torch.arange(reference.num_frames)
    spec = scaled_spec(reference.spec, scale)
    landmarks = spec.landmarks(reference.body_poses(frames, scale)).to(dt)  # (T, P, 2, 3)
    radii = spec.shapes.radii.to(dt)
    joints = reference.body_frames(frames, scale).positions.to(dt)
    far = float(h + w)

    # distance to the nearest silhouette pixel (0 inside); empty images are ignored (cam_w 0)
    def outside(sl: slice) -> Tensor:
        d = distance_to_edges(mask[sl].reshape(-1, 1, h, w)).reshape(-1, c, h, w).to(dt)
        return torch.nan_to_num(d, posinf=far)

    dout = _pair_maps(outside, tv)
    edist = None
    if obs.edge_distance is not None:
        e = obs.edge_distance[0].to(dt)  # no copy when the dtypes agree
        if torch.isnan(e).any() or (e < 0).any():
            raise RegistrationError(f"{video.name}: edge_distance must be >= 0 and not NaN")

        def to_edges(sl: slice) -> Tensor:
            return torch.nan_to_num(e[sl], posinf=far).clamp(max=far)

        edist = _pair_maps(to_edges, tv)
    # fixed random subsample of silhouette pixels per image (without replacement); the keys
    # are drawn a chunk of frames at a time: consecutive draws from one generator are the
    # same numbers (and leave it in the same state) as one draw of all of them
    m = settings.observed_points
    tops, idxs = [], []
    for lo in range(0, tv, FRAME_CHUNK):
        sl = slice(lo, min(lo + FRAME_CHUNK, tv))
        n = sl.stop - sl.start
        keys = torch.rand(n * c, h * w, generator=generator, dtype=torch.float64)
        keys = keys.masked_fill_(~mask[sl].reshape(n * c, -1), -1.0)
        top, idx = keys.topk(min(m, h * w), dim=-1)
        tops.append(top)
        idxs.append(idx)
    del keys
    top, idx = torch.cat(tops), torch.cat(idxs)
    valid = (top >= 0).to(dt)
    pts = torch.stack([idx % w, idx // w], -1).to(dt).reshape(tv, c, -1, 2)
    obs_w = (valid / valid.sum(-1, keepdim=True).clamp_min(1)).reshape(tv, c, -1)
    # keypoints
    keypoints = kp_joints = None
    if obs.keypoints is not None and video.keypoint_joints is not None:
        names = reference.skeleton.names
        unknown = [n for n in video.keypoint_joints if n not in names]
        if unknown:
            raise RegistrationError(
                f"{video.name}: keypoint joints {unknown} are not joints of {reference.name} "
                f"(expected names from {names[:4]}...)"
            )
        keypoints = obs.keypoints[0].to(dt)
        if not torch.isfinite(keypoints).all():
            raise RegistrationError(f"{video.name}: keypoints contain NaN or inf")
        kp_joints = torch.tensor([names.index(n) for n in video.keypoint_joints])
    up_b = _unit(settings.reference_up).to(dt)
    seg_len = (landmarks[..., 1, :] - landmarks[..., 0, :]).norm(dim=-1)  # (T, P)
    area = (radii.sum(-1)) * seg_len + math.pi / 2 * radii.square().sum(-1)
    centre_b = (area[..., None] * landmarks.mean(-2)).sum(-2) / area.sum(-1, keepdim=True)
    height_along = landmarks @ up_b  # (T, P, 2)
    top_b = (height_along + radii).amax((-1, -2))
    extent_b = top_b - (height_along - radii).amin((-1, -2))
    centre_from_top = (top_b - centre_b @ up_b) / extent_b.clamp_min(1e-9)
    body_height = float(extent_b.median())
    # cameras: world up from the cameras' y axes, yaw 0 facing camera 0
    rig = video.cameras
    kk, rr, tt = rig.K.to(dt), rig.R.to(dt), rig.t.to(dt)
    up = -rr[:, 1, :].mean(0)
    if up.norm() < 1e-6:
        raise RegistrationError(
            f"{video.name}: the cameras' y axes cancel out; cannot tell the world's up"
        )
    up = up / up.norm()
    fwd = -rr[0, 2, :]
    fwd = fwd - (fwd @ up) * up
    if fwd.norm() < 1e-3:  # camera 0 looks straight down or up: face its x axis
        fwd = rr[0, 0, :] - (rr[0, 0, :] @ up) * up
    fwd = fwd / fwd.norm()
    f_b = _unit(settings.reference_forward).to(dt)
    f_b = f_b - (f_b @ up_b) * up_b
    if f_b.norm() < 1e-6:
        raise RegistrationError(
            "Stage1Settings.reference_forward must not be parallel to reference_up; got "
            f"{settings.reference_forward} and {settings.reference_up}"
        )
    f_b = f_b / f_b.norm()
    world = torch.stack([torch.linalg.cross(up, fwd), up, fwd], 1)  # columns
    body = torch.stack([torch.linalg.cross(up_b, f_b), up_b, f_b], 1)
    interior, _ = SampleLayout(
        along=settings.interior_along,
        across=settings.interior_across,
        cap_points=settings.interior_cap,
    ).canonical(dt)
    _, outline = SampleLayout(
        side=settings.outline_side, arc=max(settings.outline_arc, 1)
    ).canonical(dt)
    if settings.outline_arc == 0:  # side lines only (they come first)
        outline = outline[:, : 2 * settings.outline_side]

    def blends(canon):  # (3, S) and (2, S)
        s_ax = canon[0]
        return torch.stack([(1 - s_ax) ** 2, (1 - s_ax) * s_ax, s_ax**2]), torch.stack(
            [1 - s_ax, s_ax]
        )

    scene = _Scene(
        dout,
        edist,
        pts,
        obs_w,
        height,
        cam_w,
        centroid,
        top_v,
        bottom_v,
        clipped,
        side_clipped,
        keypoints,
        kp_joints,
        landmarks,
        radii,
        joints,
        centre_b,
        extent_b,
        centre_from_top,
        kk,
        rr,
        tt,
        bool(rig.orthographic),
        h,
        w,
        up,
        fwd,
        world @ body.T,
        tuple(row[:, None] for row in interior),
        tuple(row[:, None] for row in outline),
        blends(interior),
        blends(outline),
        settings,
        body_height,
    )
    scene.video_rate = float(video.frame_rate)
    if settings.heading_weight > 0:
        scene.track = torch.full((tv, 3), math.nan, dtype=dt)
        root = reference.root.to(dt)
        v_world = _central_velocity(root, reference.frame_rate, settings.heading_window)
        rot = reference.rotations[:, 0].to(dt)  # (T, 3, 3) root to world
        scene.v_ref = (rot.transpose(1, 2) @ v_world[..., None])[..., 0]
    return scene


def _central_velocity(x: Tensor, rate: float, window: float) -> Tensor:
    """Velocity of a track ``x (F, 3)`` sampled at ``rate`` Hz by central differences over
    ``window`` seconds (one-sided at the ends). ``(F, 3)`` per second."""
    f = x.shape[0]
    k = max(1, round(window * rate / 2))
    i = torch.arange(f)
    lo, hi = (i - k).clamp(min=0), (i + k).clamp(max=f - 1)
    span = (hi - lo).clamp(min=1).to(x.dtype) / rate
    return (x[hi] - x[lo]) / span[:, None]


def _window(scene: _Scene, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The frames ``rows - k``, ``rows + k`` (clamped) that the person's velocity at ``rows``
    is measured between (``2k + 1`` frames ~ ``heading_window`` seconds), and their span in
    seconds."""
    k = max(1, round(scene.settings.heading_window * scene.video_rate / 2))
    lo = (rows - k).clamp(min=0)
    hi = (rows + k).clamp(max=scene.num_video - 1)
    return lo, hi, (hi - lo).clamp(min=1).to(scene.landmarks.dtype) / scene.video_rate


def _track_at(scene: _Scene, frames: Tensor) -> Tensor:
    """The person's root position at video ``frames`` ``(n,)`` -> ``(n, 3)`` metres, from the
    best rigid fit against ``settings.yaw_starts`` evenly spaced reference frames (heading
    prior off; a mirror-image solution has nearly the same position), computed once per
    frame when first needed."""
    need = frames[torch.isnan(scene.track[frames, 0])].unique()
    if need.numel():
        st = scene.settings
        refs = torch.linspace(0, scene.num_ref - 1, st.yaw_starts).round().long().unique()
        scene.tracking = True
        try:
            fit = _best(
                *_fit_candidates(
                    scene,
                    need,
                    refs.expand(len(need), -1),
                    st.yaw_starts,
                    st.refine_starts,
                    st.iterations,
                    [],
                )
            )
        finally:
            scene.tracking = False
        k = fit.cost.argmin(-1)
        scene.track[need] = fit.translation[torch.arange(len(need)), k]
    return scene.track[frames]


def _heading_penalty(scene: _Scene, rows: Tensor, cols: Tensor, rot: Tensor) -> Tensor:
    """The heading prior (``Stage1Settings.heading_weight``) of candidates ``rot (..., 3, 3)``
    for pairs ``rows``, ``cols`` (broadcast to ``rot``'s leading shape). ``(...)``."""
    st = scene.settings
    if scene.v_ref is None or scene.tracking:
        return torch.zeros(rot.shape[:-2], dtype=rot.dtype)
    lo, hi, span = _window(scene, rows.reshape(-1))
    v_obs = (_track_at(scene, hi) - _track_at(scene, lo)) / span[:, None]
    v_obs = (v_obs - (v_obs @ scene.up)[:, None] * scene.up).reshape(*rows.shape, 3)
    pred = (rot @ scene.v_ref[cols][..., None])[..., 0]
    pred = pred - (pred @ scene.up)[..., None] * scene.up
    n_obs, n_pred = v_obs.norm(dim=-1), pred.norm(dim=-1)
    cos = (v_obs * pred).sum(-1) / (n_obs * n_pred).clamp_min(1e-9)
    gate = (n_obs / st.heading_speed).clamp(max=1) * (n_pred / st.heading_speed).clamp(max=1)
    tolerance = math.cos(math.radians(st.heading_tolerance_deg))
    return st.heading_weight * gate * ((tolerance - cos) / (1 + tolerance)).clamp_min(0)


# -- the cost of a batch of problems and its Gauss-Newton terms -----------------------------
def _blend_index() -> Tensor:
    """``(16,)``: for the 4 x 4 channel pairs ``(a_u, a_v, b_u, b_v)^2`` of a part's
    normal-equation block, which of its 9 sums ``[g_u g_u, g_u g_v, g_v g_v] x [w_a w_a,
    w_a w_b, w_b w_b]`` (index ``3 gg + ww``) it is; a residual's point moves with the part's
    end pixels as ``w_a a + w_b b`` and ``g`` is the residual's gradient in pixels."""
    ch = torch.arange(4)
    e, k = ch // 2, ch % 2
    return ((k[:, None] + k[None, :]) * 3 + (e[:, None] + e[None, :])).reshape(-1)


_BLEND = _blend_index()
#: A soft step (1 beyond ~1/_STEP px, 0 below): float arithmetic instead of slow bool masks
#: for the Jacobian's gates at truncations and image borders.
_STEP = 1e3


def _step(x: Tensor) -> Tensor:
    return (x * _STEP).clamp_(0.0, 1.0)


class _Batch:
    """``n`` problems (pair, start) of one chunk: video frames ``rows (n,)`` and reference
    frames ``cols (n,)``; :meth:`evaluate` gives the cost and the LM normal equations.

    Internally every tensor is *batch last* (``(..., n)``): with a few dozen points per
    problem, batch-first tensors make reductions over parts and samples short inner loops;
    batch last, every operation is one long vectorised loop (several times faster here).

    The normal equations are accumulated per part: every silhouette or edge residual of part
    ``p`` depends on the pose only through the pixels of the part's two ends (a point at
    ``s`` along the axis moves as ``(1 - s) a + s b``; the capsules' image radii are held
    fixed within a step), so ``J^T J = sum_p Jl_p^T Q_p Jl_p`` with ``Jl_p`` ``(4, D)`` the
    ends' pixel Jacobian and ``Q_p`` ``(4, 4)`` built from 9 sums per part
    (:func:`_blend_index`), and ``J^T r`` from 4 more.
    """

    def __init__(self, scene: _Scene, rows: Tensor, cols: Tensor, with_scale: bool = False):
        s = scene
        self.s = s
        self.n = n = rows.shape[0]
        c = s.num_cameras
        self.lm = s.landmarks[cols].reshape(n, -1, 3).permute(2, 1, 0).contiguous()  # (3, L, n)
        self.with_scale = with_scale
        self.dof = 7 if with_scale else 6
        base = (rows[None, :] * c + torch.arange(c)[:, None]) * (s.H * s.W)  # (C, n)
        self.base = base[:, None, None, :]
        obs = s.obs[rows].permute(1, 3, 2, 0)  # (C, 2, M, n)
        self.ou = obs[:, 0, None].contiguous()  # (C, 1, M, n)
        self.ov = obs[:, 1, None].contiguous()
        self.obs_w = s.obs_w[rows].permute(1, 2, 0).contiguous()  # (C, M, n)
        self.h = s.height[rows].T.contiguous()  # (C, n) px
        self.cam = s.cam_w[rows].T / self.h.square()  # (C, n) weight of squared px
        self.kp = None
        if s.keypoints is not None:
            self.kp = s.keypoints[rows].permute(1, 3, 2, 0).contiguous()  # (C, 3, K, n)
            kx = s.joints[cols][:, s.kp_joints]  # (n, K, 3)
            self.kp_x = kx.permute(2, 1, 0).contiguous()  # (3, K, n)
            self.cam_w = s.cam_w[rows].T.contiguous()

    def _project(self, xr: list[Tensor], p: Tensor, jac: bool):
        """Points ``xr`` (3 components ``(L, n)``: rotated, scaled, relative to the root) at
        root ``p (3, n)``: pixels ``u, v`` ``(C, L, n)``, inverse depth (1 if orthographic)
        and ``d (u, v) / d theta`` ``(C, L, 2, D, n)`` (or ``None``)."""
        s = self.s
        rc, tc, k = s.R[..., None, None], s.t[..., None, None], s.K[..., None, None]
        xw = [xr[j] + p[j] for j in range(3)]
        xc = [
            torch.addcmul(
                torch.addcmul(rc[:, i, 0] * xw[0], rc[:, i, 1], xw[1]), rc[:, i, 2], xw[2]
            )
            + tc[:, i]
            for i in range(3)
        ]  # (C, L, n)
        fx, fy, cx, cy, sk = k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2], k[:, 0, 1]
        if s.orthographic:
            zi = torch.ones_like(xc[2])
            uc = torch.addcmul(fx * xc[0], sk, xc[1])
            vc = fy * xc[1]
        else:
            zi = xc[2].clamp_min(1e-3).reciprocal_()
            uc = torch.addcmul(fx * xc[0], sk, xc[1]).mul_(zi)
            vc = (fy * xc[1]).mul_(zi)
        u, v = uc + cx, vc + cy
        if not jac:
            return u, v, zi, None
        # d u / d X = (fx R0 + sk R1 - (u - cx) R2) / z; d v / d X = (fy R1 - (v - cy) R2) / z
        c, num, n = u.shape
        jl = torch.empty(c, num, 2, self.dof, n, dtype=u.dtype)
        x0, x1, x2 = xr
        rows = (
            (uc, [torch.addcmul(fx * rc[:, 0, j], sk, rc[:, 1, j]) for j in range(3)]),
            (vc, [fy * rc[:, 1, j] for j in range(3)]),
        )  # per pixel coordinate: its value minus the centre, and fx R0 + sk R1 or fy R1
        for row, (centred, base) in enumerate(rows):
            if s.orthographic:
                a = [b.expand(c, num, n) for b in base]
            else:
                a = [
                    torch.addcmul(base[j], centred, rc[:, 2, j], value=-1).mul_(zi)
                    for j in range(3)
                ]
            out = jl[:, :, row]
            torch.sub(x1 * a[2], x2 * a[1], out=out[:, :, 0])  # rotation (left increment)
            torch.sub(x2 * a[0], x0 * a[2], out=out[:, :, 1])
            torch.sub(x0 * a[1], x1 * a[0], out=out[:, :, 2])
            for j in range(3):  # translation
                out[:, :, 3 + j] = a[j]
            if self.with_scale:  # d X / d log s = X_rel
                out[:, :, 6] = torch.addcmul(torch.addcmul(x0 * a[0], x1, a[1]), x2, a[2])
        return u, v, zi, jl

    def _lookup(self, pair_map: Tensor, pu: Tensor, pv: Tensor, jac: bool):
        """Bilinear read of a paired map (:func:`_pair_map`) at pixels ``pu, pv`` ``(C, P, S,
        n)``, clamped to the image (outside points read the border): value and, with ``jac``,
        its gradient ``(gu, gv)`` (0 across a clamped border)."""
        s = self.s
        u = pu.clamp(0, s.W - 1)
        v = pv.clamp(0, s.H - 1)
        u0 = u.floor().clamp_(max=s.W - 2)
        v0 = v.floor().clamp_(max=s.H - 2)
        fu, fv = u - u0, v - v0
        i = torch.addcmul(u0, v0, torch.tensor(float(s.W), dtype=u0.dtype)).long().add_(self.base)
        shape = (*i.shape, 2)
        flat = i.reshape(-1)
        top = pair_map.index_select(0, flat).view(fu.dtype).view(shape)
        bottom = pair_map.index_select(0, flat + s.W).view(fu.dtype).view(shape)
        f00, f01 = top[..., 0], top[..., 1]
        f10, f11 = bottom[..., 0], bottom[..., 1]
        d_top = f01 - f00
        d_bottom = f11 - f10
        upper = torch.addcmul(f00, fu, d_top)
        gv = torch.addcmul(f10, fu, d_bottom).sub_(upper)
        val = torch.addcmul(upper, fv, gv)
        if not jac:
            return val, None, None
        gu = torch.addcmul(d_top, fv, d_bottom.sub_(d_top))
        gu = gu.mul_(1 - _step((pu - u).abs_()))  # no gradient across a clamped border
        gv = gv.mul_(1 - _step((pv - v).abs_()))
        return val, gu, gv

    def _points(self, canon, blend, pair_map, ends, radii, weight, cut, unseen, area, jac, acc):
        """Squared truncated map distances at sample points (interior or outline) of the
        capsules (ends and radii ``(C, P, n)`` px); adds the points' 9 + 4 normal-equation sums
        per part into ``acc (13, C, P, n)``. Returns the cost ``(n,)``. A point outside the
        image is not observed: its distance is ``unseen`` times the truncation ``cut``, with
        no gradient."""
        au, av, bu, bv = (e.unsqueeze(2) for e in ends)  # (C, P, 1, n)
        r1, r2 = (r.unsqueeze(2) for r in radii)
        s_ax, s_r, alpha, beta, c_len, c_rad = canon  # (S, 1) each
        du, dv = bu - au, bv - av
        length = torch.addcmul(du * du, dv, dv).clamp_min_(1e-12).sqrt_()
        eu, ev = du / length, dv / length
        r = torch.addcmul(r1, s_r, r2 - r1)  # (C, P, S, n)
        ra, rb = r * alpha, r * beta
        pu = torch.addcmul(torch.addcmul(au, s_ax, du), ra, eu).sub_(rb * ev)
        pv = torch.addcmul(torch.addcmul(av, s_ax, dv), ra, ev).add_(rb * eu)
        w = r * torch.addcmul(c_len * length, c_rad, r) if area else c_len * length + c_rad * r
        w = w / w.sum((1, 2), keepdim=True).clamp_min(1e-12)
        val, gu, gv = self._lookup(pair_map, pu, pv, jac)
        s = self.s
        seen = (pu >= 0) & (pu <= s.W - 1) & (pv >= 0) & (pv <= s.H - 1)
        sw = (w * (weight * self.cam)[:, None, None]).sqrt_()
        res = sw * torch.where(seen, val.minimum(cut), unseen * cut)
        if jac:
            live = sw * _step(cut - val) * seen  # no gradient beyond the truncation
            gu, gv = gu.mul_(live), gv.mul_(live)
            quad, lin = blend
            for gg, (ga, gb) in enumerate(((gu, gu), (gu, gv), (gv, gv))):
                acc[3 * gg : 3 * gg + 3] += torch.matmul(quad, ga * gb).permute(2, 0, 1, 3)
            for kk, gk in enumerate((gu, gv)):
                acc[9 + 2 * kk : 11 + 2 * kk] += torch.matmul(lin, gk * res).permute(2, 0, 1, 3)
        return res.square().sum((0, 1, 2))

    def evaluate(self, rot: Tensor, p: Tensor, log_s: Tensor | None, jac: bool):
        """Cost ``(n,)`` at poses ``rot (n, 3, 3)``, ``p (n, 3)`` (and log-scale ``(n,)``), and
        with ``jac`` the normal equations ``J^T J (n, D, D)`` and gradient ``J^T r (n, D)``."""
        s, st = self.s, self.s.settings
        n, dof = self.n, self.dof
        c = s.num_cameras
        dt = rot.dtype
        r = rot.permute(1, 2, 0)  # (3, 3, n)
        sc = log_s.exp() if log_s is not None else None
        lm = self.lm if sc is None else self.lm * sc
        xr = [
            torch.addcmul(torch.addcmul(r[i, 0] * lm[0], r[i, 1], lm[1]), r[i, 2], lm[2])
            for i in range(3)
        ]  # (L, n)
        u, v, zi, jl = self._project(xr, p.T, jac)  # (C, L, n)
        num_p = u.shape[1] // 2
        u, v = u.view(c, num_p, 2, n), v.view(c, num_p, 2, n)
        ends = (u[:, :, 0], v[:, :, 0], u[:, :, 1], v[:, :, 1])  # a_u, a_v, b_u, b_v (C, P, n)
        px = s.radii.T[:, None, :, None] * s.K[:, 0, 0][:, None, None]  # (2, C, P, 1)
        if not s.orthographic:
            px = px * zi.view(c, num_p, 2, n).permute(2, 0, 1, 3)
        if sc is not None:
            px = px * sc
        radii = (px[0].expand(c, num_p, n), px[1].expand(c, num_p, n))
        cost = torch.zeros(n, dtype=dt)
        acc = torch.zeros(13, c, num_p, n, dtype=dt) if jac else None
        cut = (st.truncate * self.h)[:, None, None]  # (C, 1, 1, n) px
        if st.outside_weight > 0:
            cost = cost + self._points(
                s.interior,
                s.interior_blend,
                s.dout,
                ends,
                radii,
                st.outside_weight,
                cut,
                0.0,  # no silhouette evidence either way
                True,
                jac,
                acc,
            )
        if s.edist is not None and st.edge_weight > 0:
            cut_e = (st.edge_truncate * self.h)[:, None, None]
            cost = cost + self._points(
                s.outline,
                s.outline_blend,
                s.edist,
                ends,
                radii,
                st.edge_weight,
                cut_e,
                0.5,  # as a hidden stretch of outline costs in stage 2's Edges cue
                False,
                jac,
                acc,
            )
        if st.uncovered_weight > 0:
            cost = cost + self._uncovered(ends, radii, cut[:, 0], jac, acc)
        jtj = g = None
        if jac:
            x = c * num_p * 4
            q = acc[_BLEND].view(4, 4, c, num_p, n).permute(2, 3, 0, 1, 4)  # (C, P, 4, 4, n)
            b = acc[9:].view(2, 2, c, num_p, n).permute(2, 3, 1, 0, 4).reshape(x, 1, n)
            jl = jl.view(c, num_p, 4, dof, n)  # channels (a_u, a_v, b_u, b_v)
            t1 = q[:, :, :, 0:1] * jl[:, :, 0:1]
            for j in range(1, 4):
                t1 = torch.addcmul(t1, q[:, :, :, j : j + 1], jl[:, :, j : j + 1])
            jl = jl.reshape(x, dof, n)
            jtj = (jl.unsqueeze(2) * t1.reshape(x, 1, dof, n)).sum(0)  # (D, D, n)
            g = (jl * b).sum(0)  # (D, n)
        if self.kp is not None and st.keypoint_weight > 0:
            kc, kj, kg = self._keypoints(r, p.T, sc, jac)
            cost = cost + kc
            if jac:
                jtj = jtj + kj
                g = g + kg
        if not jac:
            return cost, None, None
        return cost, jtj.permute(2, 0, 1), g.T

    def _uncovered(self, ends, radii, cut, jac, acc):
        """Silhouette pixels (the fixed subsample) against their distance to the nearest
        capsule (0 when covered), truncated at ``cut (C, 1, n)`` px. Returns the cost."""
        st = self.s.settings
        au, av, bu, bv = (e.unsqueeze(2) for e in ends)  # (C, P, 1, n)
        r1, r2 = (r.unsqueeze(2) for r in radii)
        c, p, _, n = au.shape
        du, dv = bu - au, bv - av
        inv = torch.addcmul(du * du, dv, dv).clamp_min_(1e-9).reciprocal_()
        ru, rv = self.ou - au, self.ov - av  # (C, P, M, n)
        t = torch.addcmul(ru * du, rv, dv).mul_(inv).clamp_(0, 1)
        xu = torch.addcmul(ru, t, du, value=-1)
        xv = torch.addcmul(rv, t, dv, value=-1)
        dist = torch.addcmul(xu * xu, xv, xv).clamp_min_(1e-12).sqrt_()
        sd = dist - torch.addcmul(r1, t, r2 - r1)
        near = sd.amin(1)  # (C, M, n)
        sw = (st.uncovered_weight * self.obs_w * self.cam[:, None]).sqrt_()
        res = sw * near.clamp(0).minimum(cut)
        if jac:
            # the nearest part's index: parts - 1e6 (sd - near) peaks there (float arithmetic;
            # argmin over a leading dimension is ~100x slower than amin here)
            parts = torch.arange(p, dtype=sd.dtype)[:, None, None]
            k = torch.addcmul(parts, sd - near.unsqueeze(1), torch.tensor(-1e6, dtype=sd.dtype))
            k = k.amax(1).round_().long().clamp_(0, p - 1)  # (C, M, n)
            kk = k.unsqueeze(1)
            t_k = t.gather(1, kk)[:, 0]
            # d sd / d (a, b) = -(1 - t) e, -t e (e the unit direction from the axis)
            scale = sw * _step(near) * _step(cut - near) / dist.gather(1, kk)[:, 0]
            gu = xu.gather(1, kk)[:, 0].mul_(scale).neg_()
            gv = xv.gather(1, kk)[:, 0].mul_(scale).neg_()
            wa, wb = 1 - t_k, t_k
            vals = torch.empty(13, *res.shape, dtype=res.dtype)
            ww = (wa * wa, wa * wb, wb * wb)
            for gg, g2 in enumerate((gu * gu, gu * gv, gv * gv)):
                for j in range(3):
                    torch.mul(g2, ww[j], out=vals[3 * gg + j])
            for kk_, gk in enumerate((gu * res, gv * res)):
                torch.mul(gk, wa, out=vals[9 + 2 * kk_])
                torch.mul(gk, wb, out=vals[10 + 2 * kk_])
            # into (13, C, P, n): column (c P + k) n + j
            col = ((torch.arange(c)[:, None, None] * p + k) * n + torch.arange(n)).reshape(-1)
            acc.view(13, -1).index_add_(1, col, vals.view(13, -1))
        return res.square().sum((0, 1))

    def _keypoints(self, r, p, sc, jac):
        """Cauchy-robust 2-D joint term at rotation ``r (3, 3, n)``, root ``p (3, n)``: cost
        ``(n,)`` and (IRLS) ``J^T J (D, D, n)``, ``J^T r (D, n)``."""
        st = self.s.settings
        x = self.kp_x if sc is None else self.kp_x * sc
        xr = [
            torch.addcmul(torch.addcmul(r[i, 0] * x[0], r[i, 1], x[1]), r[i, 2], x[2])
            for i in range(3)
        ]
        u, v, _, jj = self._project(xr, p, jac)  # (C, K, n)
        eu, ev = u - self.kp[:, 0], v - self.kp[:, 1]
        conf = self.kp[:, 2].clamp_min(0) * self.cam_w[:, None]
        norm = conf.sum(1, keepdim=True).clamp_min(1e-9)
        sig2 = (st.keypoint_sigma * self.h).square()[:, None]  # (C, 1, n) px^2
        d2 = torch.addcmul(eu * eu, ev, ev)
        w = st.keypoint_weight * conf / norm / self.h.square()[:, None]
        cost = (w * sig2 * torch.log1p(d2 / sig2)).sum((0, 1))
        if not jac:
            return cost, None, None
        irls = (w / (1 + d2 / sig2)).sqrt()  # Cauchy weights at the current residuals
        jr = jj * irls[:, :, None, None]  # (C, K, 2, D, n)
        res = torch.stack([irls * eu, irls * ev], 2)[:, :, :, None]  # (C, K, 2, 1, n)
        jr = jr.reshape(-1, self.dof, jr.shape[-1])
        jtj = (jr.unsqueeze(2) * jr.unsqueeze(1)).sum(0)
        return cost, jtj, (jr * res.reshape(-1, 1, res.shape[-1])).sum(0)


def _levenberg_marquardt(
    batch: _Batch, rot: Tensor, p: Tensor, log_s: Tensor | None, iterations: int, damping: float
):
    """Batched LM from ``rot (n, 3, 3)``, ``p (n, 3)`` (``log_s (n,)``): each problem keeps a
    step only if it lowers its cost. Returns rot, p, log_s, cost ``(n,)``."""
    cost, jtj, g = batch.evaluate(rot, p, log_s, True)
    lam = torch.full_like(cost, damping)
    for it in range(iterations):
        diag = jtj.diagonal(dim1=-2, dim2=-1)
        floor = 1e-6 * diag.mean(-1, keepdim=True) + 1e-12
        a = jtj + torch.diag_embed(lam[:, None] * diag + floor)
        step = -torch.linalg.solve(a, g)
        rot_n = rotation_vector_to_matrix(step[:, :3]) @ rot
        p_n = p + step[:, 3:6]
        ls_n = log_s + step[:, 6] if log_s is not None else None
        last = it == iterations - 1
        cost_n, jtj_n, g_n = batch.evaluate(rot_n, p_n, ls_n, not last)
        better = cost_n < cost
        b3 = better[:, None, None]
        rot = torch.where(b3, rot_n, rot)
        p = torch.where(better[:, None], p_n, p)
        if log_s is not None:
            log_s = torch.where(better, ls_n, log_s)
        if not last:
            jtj = torch.where(b3, jtj_n, jtj)
            g = torch.where(better[:, None], g_n, g)
        gain = torch.where(better, cost - cost_n, torch.zeros_like(cost))
        cost = torch.where(better, cost_n, cost)
        lam = torch.where(better, lam * 0.3, lam * 10).clamp(1e-7, 1e7)
        # converged: an accepted step that barely helped, or damping so high steps vanish
        if bool(((better & (gain <= 1e-6 * cost + 1e-12)) | (lam >= 1e5)).all()):
            break
    return rot, p, log_s, cost


# -- starts ---------------------------------------------------------------------------------
def _targets(
    scene: _Scene, rows: Tensor, cols: Tensor, depth_factor: float = 1.0, side_shift: float = 0.0
) -> Tensor:
    """Where the body's centroid should be for pairs ``rows (R,)``, ``cols (R, W)``: the
    least-squares meeting point of the rays through the silhouette centroids, with each
    (perspective) camera's depth guessed from the silhouette's pixel height against the
    body's height. Where a silhouette touches the image's top or bottom edge, that depth is
    multiplied by ``depth_factor`` (the height seen is a lower bound of the body's) and, with
    one edge clipped, the centroid is hung from the edge in view: the body's pixel height
    below its top row (or above its bottom row) times the centroid's place in ``B_t``.
    Where it touches one side edge, the centroid is moved toward that edge by
    ``side_shift`` times the body's pixel height. ``(R, W, 3)`` metres."""
    s = scene
    dt = s.landmarks.dtype
    r, w = cols.shape
    kinv = torch.linalg.inv(s.K)  # (C, 3, 3)
    clip = s.clipped[rows][:, None]  # (R, 1, C, 2) top, bottom
    clipped = clip.any(-1)  # (R, 1, C)
    height = s.height[rows][:, None]  # (R, 1, C) px
    if s.orthographic:
        body_px = s.K[:, 1, 1] * s.extent_b[cols][..., None]  # (R, W, C)
    else:
        body_px = torch.where(clipped, height / depth_factor, height).expand(r, w, -1)
    frac = s.centre_from_top[cols][..., None]  # (R, W, 1)
    v = s.centroid[rows][:, None, :, 1].expand(r, w, -1)  # (R, W, C)
    v = torch.where(clip[..., 1] & ~clip[..., 0], s.top_v[rows][:, None] + frac * body_px, v)
    v = torch.where(
        clip[..., 0] & ~clip[..., 1], s.bottom_v[rows][:, None] - (1 - frac) * body_px, v
    )
    u = s.centroid[rows][:, None, :, 0].expand(r, w, -1)
    if side_shift:
        side = s.side_clipped[rows][:, None].to(dt)  # (R, 1, C, 2) left, right
        u = u + side_shift * body_px * (side[..., 1] - side[..., 0])
    hom = torch.stack([u, v, torch.ones_like(u)], -1)  # (R, W, C, 3)
    ray_c = torch.einsum("cij,rwcj->rwci", kinv, hom)  # camera frame, z = 1
    if s.orthographic:
        origin_c = ray_c.clone()
        origin_c[..., 2] = 0.0
        origin = torch.einsum("cji,rwcj->rwci", s.R, origin_c - s.t)  # R^T (x - t)
        d = s.R[:, 2, :].expand_as(origin)
        lam0 = -(d * origin).sum(-1, keepdim=True)  # depth of the world origin
        mu = torch.full_like(lam0, 1e-3)
    else:
        origin = (-(s.R.transpose(1, 2) @ s.t[..., None])[..., 0]).expand(r, w, -1, -1)
        ray = torch.einsum("cji,rwcj->rwci", s.R, ray_c)
        length = ray.norm(dim=-1, keepdim=True)
        d = ray / length
        # depth: pixel height = f * body extent / z
        z = s.K[:, 1, 1] * s.extent_b[cols][..., None] / body_px  # (R, W, C)
        lam0 = z[..., None] * length
        mu = torch.full_like(length, s.settings.depth_prior)
    cam = s.cam_w[rows][:, None, :, None]  # (R, 1, C, 1)
    eye = torch.eye(3, dtype=dt)
    ddt = d[..., :, None] * d[..., None, :]  # (R, W, C, 3, 3)
    proj = eye - ddt
    m = (cam[..., None] * (proj + mu[..., None] * ddt)).sum(2)  # (R, W, 3, 3)
    b_perp = (cam * (proj @ origin[..., None])[..., 0]).sum(2)  # (R, W, 3)
    along = (d * origin).sum(-1, keepdim=True)  # (R, W, C, 1)
    rhs = b_perp + (cam * mu * d * (along + lam0)).sum(2)
    return torch.linalg.solve(m + 1e-9 * eye, rhs)


def _yaw_rotations(scene: _Scene, count: int) -> Tensor:
    """``(count, 3, 3)``: the reference's up onto the world's up, yaws evenly spaced."""
    yaw = torch.arange(count, dtype=scene.up.dtype) * (2 * math.pi / count)
    return rotation_vector_to_matrix(scene.up * yaw[:, None]) @ scene.align


def _keypoint_starts(scene: _Scene, rows: Tensor, cols: Tensor) -> Init | None:
    """Pose from the 2-D joints of pairs ``rows (R,)``, ``cols (R, W)``: perspective rigs by
    :func:`motion.pose.solve_pose_views` (all cameras, confidences as weights), orthographic
    ones by :func:`motion.pose.solve_pose` on the most confident camera. ``(R, W, 3, 3)``,
    ``(R, W, 3)`` metres, or ``None`` without keypoints (or with fewer than 6)."""
    s = scene
    if s.keypoints is None or s.kp_joints.numel() < 6:
        return None
    r, w = cols.shape
    x3 = s.joints[cols.reshape(-1)][:, s.kp_joints].to(torch.float64)  # (R W, K, 3)
    kp = s.keypoints[rows].to(torch.float64)[:, None].expand(-1, w, -1, -1, -1)
    kp = kp.reshape(r * w, *kp.shape[2:])  # (R W, C, K, 3)
    k64, r64, t64 = s.K.double(), s.R.double(), s.t.double()
    try:
        if s.orthographic:
            best = int(kp[..., 2].sum((0, 2)).argmax())
            res = solve_pose(x3, kp[:, best, :, :2], k64[best], orthographic=True)
            rot = r64[best].T @ res.R  # camera to world
            p = ((res.t - t64[best]) @ r64[best]).to(s.landmarks.dtype)
        else:
            res = solve_pose_views(x3, kp[..., :2], k64, r64, t64, weights=kp[..., 2])
            rot, p = res.R, res.t.to(s.landmarks.dtype)
    except ValueError:  # degenerate joints: no such start
        return None
    rot = rot.to(s.landmarks.dtype).reshape(r, w, 3, 3)
    return rot, p.reshape(r, w, 3)


def _as_pair_init(init: Init | None, rows: Tensor, cols: Tensor, dt) -> Init | None:
    """A warm start ``(R, W, 3, 3)``+``(R, W, 3)`` or per row ``(R, 3, 3)``+``(R, 3)``, checked
    and expanded to ``(R, W, ...)``."""
    if init is None:
        return None
    r, w = cols.shape
    if not (isinstance(init, tuple | list) and len(init) == 2):
        raise RegistrationError(
            f"init must be a (rotation, translation) pair of tensors; got {type(init).__name__}"
        )
    rot, p = (torch.as_tensor(x) for x in init)
    if rot.shape == (r, 3, 3) and p.shape == (r, 3):
        rot, p = rot[:, None].expand(r, w, 3, 3), p[:, None].expand(r, w, 3)
    if rot.shape != (r, w, 3, 3) or p.shape != (r, w, 3):
        raise RegistrationError(
            f"init must be rotation ({r}, {w}, 3, 3) and translation ({r}, {w}, 3), or per row "
            f"({r}, 3, 3) and ({r}, 3); got {tuple(rot.shape)} and {tuple(p.shape)}"
        )
    if not (torch.isfinite(rot).all() and torch.isfinite(p).all()):
        raise RegistrationError("init contains NaN or inf")
    return rot.to(dt), p.to(dt)


def _check_pairs(scene: _Scene, rows, cols) -> tuple[Tensor, Tensor]:
    if not isinstance(rows, Tensor) or not isinstance(cols, Tensor):
        raise RegistrationError(
            f"rows and cols must be tensors; got {type(rows).__name__} and {type(cols).__name__}"
        )
    if rows.dim() != 1 or cols.dim() != 2 or cols.shape[0] != rows.shape[0]:
        raise RegistrationError(
            f"expected rows (R,) and cols (R, W); got {tuple(rows.shape)} and {tuple(cols.shape)}"
        )
    if rows.numel() == 0 or cols.numel() == 0:
        raise RegistrationError(
            f"expected at least one pair; got rows {tuple(rows.shape)} and cols {tuple(cols.shape)}"
        )
    if rows.dtype.is_floating_point or cols.dtype.is_floating_point or rows.dtype == torch.bool:
        raise RegistrationError(
            f"rows and cols must be integer frame indices; got {rows.dtype} and {cols.dtype}"
        )
    rows, cols = rows.long(), cols.long()
    if int(rows.min()) < 0 or int(rows.max()) >= scene.num_video:
        raise RegistrationError(
            f"rows must be video frames in [0, {scene.num_video}); got "
            f"{int(rows.min())}..{int(rows.max())}"
        )
    if int(cols.min()) < 0 or int(cols.max()) >= scene.num_ref:
        raise RegistrationError(
            f"cols must be reference frames in [0, {scene.num_ref}); got "
            f"{int(cols.min())}..{int(cols.max())}"
        )
    return rows, cols


def _analytic_starts(scene: _Scene, rows: Tensor, cols: Tensor, yaw_starts: int, keep: int) -> Init:
    """The ``keep`` best of ``yaw_starts`` upright starts per pair (reference up on world up,
    yaws evenly spaced, centroid at the triangulated silhouette centroid), by their cost.
    Returns ``(R, W, keep, 3, 3)``, ``(R, W, keep, 3)``. Chunked."""
    r, w = cols.shape
    yaws = _yaw_rotations(scene, yaw_starts)  # (S, 3, 3)
    # rows whose silhouette an image edge cuts get starts at several depths (top or bottom
    # edge) and centroid shifts (a side edge); the first of each for every row
    st = scene.settings
    depths = (1.0,) if scene.orthographic else st.clipped_depths
    clipped = scene.clipped[rows].any(-1).any(-1)  # (R,)
    side_clipped = scene.side_clipped[rows].any(-1).any(-1)  # (R,)
    every = torch.ones_like(clipped)
    variants = [  # (depth, shift, the rows it applies to)
        (depth, shift, (clipped if i else every) & (side_clipped if j else every))
        for i, depth in enumerate(depths)
        for j, shift in enumerate(st.clipped_shifts)
    ]
    rows_per_chunk = max(1, st.chunk // (yaw_starts * w))
    out_r, out_p = [], []
    for lo in range(0, r, rows_per_chunk):  # chunks of rows keep memory bounded
        rr, cc = rows[lo : lo + rows_per_chunk], cols[lo : lo + rows_per_chunk]
        nr = rr.shape[0]
        rot0 = yaws[None, None].expand(nr, w, -1, -1, -1)  # the same yaws in every variant
        costs, ps = [], []
        for depth, shift, applies in variants:
            sub = applies[lo : lo + nr].nonzero().flatten()
            if not len(sub):  # no row of this chunk is cut that way
                continue
            p0 = torch.zeros(nr, w, yaw_starts, 3, dtype=yaws.dtype)
            cost0 = torch.full((nr, w, yaw_starts), math.inf, dtype=yaws.dtype)
            target = _targets(scene, rr[sub], cc[sub], depth, shift)  # (n, W, 3)
            centre = (rot0[sub] @ scene.centre_b[cc[sub]][:, :, None, :, None])[..., 0]
            p0[sub] = target[:, :, None] - centre
            rows_n = rr[sub][:, None, None].expand(-1, w, yaw_starts).reshape(-1)
            cols_n = cc[sub][:, :, None].expand(-1, w, yaw_starts).reshape(-1)
            flat_r = rot0[sub].reshape(-1, 3, 3)
            c0, _, _ = _Batch(scene, rows_n, cols_n).evaluate(
                flat_r, p0[sub].reshape(-1, 3), None, False
            )
            c0 = c0 + _heading_penalty(scene, rows_n, cols_n, flat_r)
            cost0[sub] = c0.reshape(-1, w, yaw_starts)
            costs.append(cost0)
            ps.append(p0)
        cost0, p0 = torch.cat(costs, 2), torch.cat(ps, 2)
        rot0 = rot0.repeat(1, 1, len(costs), 1, 1)
        best = cost0.topk(keep, dim=-1, largest=False).indices
        out_r.append(rot0.gather(2, best[..., None, None].expand(-1, -1, -1, 3, 3)))
        out_p.append(p0.gather(2, best[..., None].expand(-1, -1, -1, 3)))
    return torch.cat(out_r), torch.cat(out_p)


def _refine_from(
    scene: _Scene, rows: Tensor, cols: Tensor, rot0: Tensor, p0: Tensor, iterations: int
) -> tuple[Tensor, Tensor, Tensor]:
    """LM from starts ``rot0 (R, W, K, 3, 3)``, ``p0 (R, W, K, 3)`` of pairs ``rows (R,)``,
    ``cols (R, W)``: cost ``(R, W, K)``, rotation and translation of each. Chunked."""
    r, w, k = rot0.shape[:3]
    rows_n = rows[:, None, None].expand(r, w, k).reshape(-1)
    cols_n = cols[:, :, None].expand(r, w, k).reshape(-1)
    rot0, p0 = rot0.reshape(-1, 3, 3), p0.reshape(-1, 3)
    step = scene.settings.chunk
    out_c, out_r, out_p = [], [], []
    for lo in range(0, rows_n.shape[0], step):
        sl = slice(lo, lo + step)
        batch = _Batch(scene, rows_n[sl], cols_n[sl])
        rot, p, _, cost = _levenberg_marquardt(
            batch, rot0[sl], p0[sl], None, iterations, scene.settings.lm_damping
        )
        out_c.append(cost + _heading_penalty(scene, rows_n[sl], cols_n[sl], rot))
        out_r.append(rot)
        out_p.append(p)
    return (
        torch.cat(out_c).reshape(r, w, k),
        torch.cat(out_r).reshape(r, w, k, 3, 3),
        torch.cat(out_p).reshape(r, w, k, 3),
    )


def _fit_candidates(
    scene: _Scene,
    rows: Tensor,
    cols: Tensor,
    yaw_starts: int,
    refine: int,
    iterations: int,
    inits: list[Init],
    anchor_stride: int = 1,
    count: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Refined starts of every pair ``rows (R,)``, ``cols (R, W)``.

    With ``anchor_stride`` 1 (or ``W <= anchor_stride``): the ``refine`` best of
    ``yaw_starts`` screened upright starts, each warm start in ``inits`` (``(R, W, 3, 3)``,
    ``(R, W, 3)``) and (with keypoints) the 2-D joint pose, all refined by LM. Otherwise
    every ``anchor_stride``-th column (the anchors) is fitted that way and every pair is
    refined (``settings.warm_iterations``) from the best ``T`` of the two anchors around it
    -- for columns that are runs of neighbouring reference frames, whose best ``T`` differ
    little.

    Costs include the heading prior (``Stage1Settings.heading_weight``). With ``count``,
    the ``R W`` pairs are added to ``scene.fits``.

    Returns cost ``(R, W, K)``, rotation ``(R, W, K, 3, 3)``, translation ``(R, W, K, 3)``.
    """
    w = cols.shape[1]
    if count:
        scene.fits += cols.numel()
    if anchor_stride > 1 and w > anchor_stride:
        pos = torch.arange(anchor_stride // 2, w, anchor_stride)
        a_inits = [(i[0][:, pos], i[1][:, pos]) for i in inits]
        fit = _best(
            *_fit_candidates(
                scene, rows, cols[:, pos], yaw_starts, refine, iterations, a_inits, count=False
            )
        )
        j = torch.arange(w)
        lo = (torch.searchsorted(pos, j, right=True) - 1).clamp(0, len(pos) - 1)
        hi = (lo + 1).clamp(max=len(pos) - 1)
        near = torch.stack([lo, hi], -1)  # (W, 2) the anchors on either side
        return _refine_from(
            scene,
            rows,
            cols,
            fit.rotation[:, near],
            fit.translation[:, near],
            scene.settings.warm_iterations,
        )
    rots, ps = list(_analytic_starts(scene, rows, cols, yaw_starts, refine))
    rots, ps = [rots], [ps]
    for er, ep in inits:
        rots.append(er[:, :, None])
        ps.append(ep[:, :, None])
    kp = _keypoint_starts(scene, rows, cols)
    if kp is not None:
        rots.append(kp[0][:, :, None])
        ps.append(kp[1][:, :, None])
    return _refine_from(scene, rows, cols, torch.cat(rots, 2), torch.cat(ps, 2), iterations)


def _stride(cols: Tensor, settings: Stage1Settings) -> int:
    """``settings.anchor_stride`` where every row of ``cols (R, W)`` is a run of neighbouring
    reference frames (steps of at most ``settings.anchor_gap``), else 1."""
    steps = (cols[:, 1:] - cols[:, :-1]).abs()
    if steps.numel() and int(steps.max()) > settings.anchor_gap:
        return 1
    return settings.anchor_stride


def _best(cost: Tensor, rot: Tensor, p: Tensor) -> PairFit:
    k = cost.argmin(-1, keepdim=True)
    return PairFit(
        cost.gather(-1, k).squeeze(-1),
        rot.gather(2, k[..., None, None].expand(*k.shape, 3, 3)).squeeze(2),
        p.gather(2, k[..., None].expand(*k.shape, 3)).squeeze(2),
    )


def _generator(generator: torch.Generator | None) -> torch.Generator:
    if generator is None:
        return torch.Generator().manual_seed(0)
    if not isinstance(generator, torch.Generator):
        raise RegistrationError(
            f"generator must be a torch.Generator or None; got {type(generator).__name__}"
        )
    return generator


def _settings(settings: Stage1Settings | None) -> Stage1Settings:
    if settings is None:
        return Stage1Settings()
    if not isinstance(settings, Stage1Settings):
        raise RegistrationError(
            f"settings must be Stage1Settings or None; got {type(settings).__name__}"
        )
    return settings


# -- public API -----------------------------------------------------------------------------
def fit_rigid_pairs(
    reference: Reference,
    video: VideoFeatures,
    rows: Tensor,
    cols: Tensor,
    scale: float = 1.0,
    settings: Stage1Settings | None = None,
    generator: torch.Generator | None = None,
    init: Init | None = None,
) -> PairFit:
    """The best rigid ``T`` of ``G B_t`` against video frame ``t'`` for every pair.

    Each pair's cost is the minimum over starts of the image cost plus the heading prior
    (module docstring): the reference's up on the world's up at ``settings.yaw_starts``
    yaws, placed at the silhouette centroid (triangulated, depth from the silhouette
    height), the best ``settings.refine_starts`` of those refined by LM, plus ``init`` and
    (with keypoints) the pose from the 2-D joints. Where each row's ``cols`` are a run of
    neighbouring reference frames, only every ``settings.anchor_stride``-th gets all starts
    (:class:`Stage1Settings`). The heading prior needs the person's track around the rows:
    ``settings.yaw_starts`` extra fits per video frame ``rows +- heading_window / 2``.

    Args:
        reference: the reference motion.
        video: the observation (silhouettes; optional edge distances and keypoints).
        rows: ``(R,)`` long video frames.
        cols: ``(R, W)`` long reference frames paired with each row.
        scale: G, the body size relative to the reference.
        settings: :class:`Stage1Settings` (default: its defaults).
        generator: draws the silhouette subsample (default: seed 0).
        init: optional warm start, rotation ``(R, W, 3, 3)`` and translation ``(R, W, 3)``
            (metres), or one per row ``(R, 3, 3)``, ``(R, 3)``; refined as an extra start.

    Returns:
        :class:`PairFit` with ``(R, W)`` costs and transforms.

    Raises:
        RegistrationError: bad shapes or indices, empty input, frames without silhouettes.
    """
    st = _settings(settings)
    scene = _build_scene(reference, video, scale, st, _generator(generator))
    rows, cols = _check_pairs(scene, rows, cols)
    inits = [] if init is None else [_as_pair_init(init, rows, cols, st.dtype)]
    cost, rot, p = _fit_candidates(
        scene, rows, cols, st.yaw_starts, st.refine_starts, st.iterations, inits, _stride(cols, st)
    )
    return _best(cost, rot, p)


def pair_costs(
    reference: Reference,
    video: VideoFeatures,
    rows: Tensor,
    cols: Tensor,
    rotation: Tensor,
    translation: Tensor,
    scale: float = 1.0,
    settings: Stage1Settings | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """The image cost of given transforms (no fitting, no heading prior): what
    :func:`fit_rigid_pairs` minimises.

    Args:
        rows ``(R,)``, cols ``(R, W)``: pairs as :func:`fit_rigid_pairs`.
        rotation: ``(R, W, 3, 3)``; translation: ``(R, W, 3)`` metres (or one per row,
            ``(R, 3, 3)`` and ``(R, 3)``).
        scale, settings, generator: as :func:`fit_rigid_pairs` (the same generator seed
            draws the same silhouette subsample).

    Returns:
        ``(R, W)`` costs (settings dtype).
    """
    st = _settings(settings)
    scene = _build_scene(reference, video, scale, st, _generator(generator))
    rows, cols = _check_pairs(scene, rows, cols)
    rot, p = _as_pair_init((rotation, translation), rows, cols, st.dtype)
    r, w = cols.shape
    flat_rows = rows[:, None].expand(r, w).reshape(-1)
    out = [
        _Batch(scene, flat_rows[lo : lo + st.chunk], cols.reshape(-1)[lo : lo + st.chunk]).evaluate(
            rot.reshape(-1, 3, 3)[lo : lo + st.chunk],
            p.reshape(-1, 3)[lo : lo + st.chunk],
            None,
            False,
        )[0]
        for lo in range(0, r * w, st.chunk)
    ]
    return torch.cat(out).reshape(r, w)


def estimate_body_scale(
    reference: Reference,
    video: VideoFeatures,
    settings: Stage1Settings | None = None,
    generator: torch.Generator | None = None,
    frames: int = 8,
) -> tuple[float, str]:
    """Body size G from ``frames`` video frames spread evenly over the video.

    Frames spread over the whole video, rather than its first ones, sample different
    postures: where the student's articulation or a wrong best reference frame biases one
    frame's fit, its neighbours share that bias and a median of consecutive frames keeps it
    (the synthetic walk, 2 cameras, true G = 1, warp seeds 0/1/2: the first 8 frames gave
    0.975 / 1.006 / 1.000, 8 spread frames 1.006 / 0.997 / 0.998).

    Each frame is fitted (``T`` at G = 1) against ``settings.scale_reference_frames``
    reference frames evenly spaced over the motion, then against every reference frame
    around its best one; at its best pair, ``T`` and a scale factor are refined together
    (``settings.scale_rounds`` times, each at the previous estimate); G is the median over
    frames. Only where the scale is observable: orthographic
    cameras (pixels per metre are known) or two or more calibrated perspective cameras. With
    one perspective camera size and depth are confounded: G = 1 and a note saying so.

    Returns:
        ``(G, note)``: the scale and how it was obtained (for reports).

    Raises:
        RegistrationError: bad input, ``frames < 1``.
    """
    st = _settings(settings)
    gen = _generator(generator)
    st = dataclasses.replace(
        st, observed_points=st.scale_observed_points, edge_weight=st.scale_edge_weight
    )
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise RegistrationError(f"frames must be an int >= 1; got {frames!r}")
    _check_inputs(reference, video, 1.0)
    rig = video.cameras
    if not rig.orthographic and rig.num_cameras < 2:
        return 1.0, (
            f"{SCALE_NOT_ESTIMATED}: one perspective camera cannot tell body size from depth"
        )
    nf = min(frames, video.num_frames)
    video = video.cut(torch.linspace(0, video.num_frames - 1, nf).round().long())
    rows = torch.arange(nf)
    nref = min(st.scale_reference_frames, reference.num_frames)
    ref = torch.linspace(0, reference.num_frames - 1, nref).round().long().unique()
    half = max(1, math.ceil((reference.num_frames - 1) / max(len(ref) - 1, 1) / 2))
    idx = torch.arange(nf)
    g_est = 1.0
    for _ in range(st.scale_rounds):
        scene = _build_scene(reference, video, g_est, st, gen)
        cols = ref.expand(nf, -1)
        fit = _best(
            *_fit_candidates(
                scene,
                rows,
                cols,
                st.yaw_starts,
                st.refine_starts,
                st.iterations,
                [],
                _stride(cols, st),
            )
        )
        k = fit.cost.argmin(-1)  # each video frame's best coarse reference frame
        # then every reference frame around it, warm-started from its T
        local = (ref[k][:, None] + torch.arange(-half, half + 1)).clamp(0, reference.num_frames - 1)
        warm = (fit.rotation[idx, k], fit.translation[idx, k])
        fit = _best(
            *_fit_candidates(
                scene,
                rows,
                local,
                st.yaw_starts,
                st.refine_starts,
                st.iterations,
                [_as_pair_init(warm, rows, local, st.dtype)],
                _stride(local, st),
            )
        )
        k = fit.cost.argmin(-1)
        batch = _Batch(scene, rows, local[idx, k], with_scale=True)
        _, _, log_s, _ = _levenberg_marquardt(
            batch,
            fit.rotation[idx, k],
            fit.translation[idx, k],
            torch.zeros(nf, dtype=st.dtype),
            st.scale_iterations,
            st.lm_damping,
        )
        g_est = float(g_est * log_s.exp().median())
    spread = float(log_s.exp().std()) if nf > 1 else 0.0
    how = "orthographic cameras" if rig.orthographic else f"{rig.num_cameras} calibrated cameras"
    return g_est, (
        f"G = {g_est:.3f} estimated from {how}: median over {nf} video frames spread evenly "
        f"over the video of a rigid fit with free scale at each frame's best reference frame (of {len(ref)} evenly "
        "spaced, then their neighbours) "
        f"(relative spread {spread:.3f})"
    )


def _viterbi_candidates(
    cost: Tensor, rot: Tensor, p: Tensor, weight: float, body_height: float
) -> Tensor:
    """Per frame the candidate minimising ``sum cost + weight * sum (angle^2 + (|dp| / h)^2)``
    over neighbouring frames: cost ``(T', K)``, rot ``(T', K, 3, 3)``, p ``(T', K, 3)`` ->
    ``(T',)`` long candidate index."""
    if cost.shape[0] == 1 or weight == 0:
        return cost.argmin(-1)
    ang = relative_angle(rot[:-1, :, None], rot[1:, None, :])  # (T'-1, K, K)
    dp = (p[:-1, :, None] - p[1:, None, :]).norm(dim=-1) / max(body_height, 1e-6)
    table = -weight * (ang.square() + dp.square())
    result = chain_map(-cost.double()[None], TableFactor(table.double()))
    return result.assignment[0]


def _final_transforms(scene: _Scene, c_path: Tensor, row_init: Init | None):
    """``T`` per video frame at ``(t', C(t'))``: many starts, then exact temporal smoothing
    over each frame's candidates, then rounds of LM warm-started from the neighbours' chosen
    ``T`` (added as candidates, smoothed again). Returns cost ``(T',)``, rotation
    ``(T', 3, 3)`` and translation ``(T', 3)``."""
    st = dataclasses.replace(scene.settings, edge_weight=scene.settings.final_edge_weight)
    scene.settings = st  # the final fit's own edge weight (see Stage1Settings)
    tv = c_path.shape[0]
    rows = torch.arange(tv)
    cols = c_path[:, None]
    inits = [] if row_init is None else [_as_pair_init(row_init, rows, cols, st.dtype)]
    cost, rot, p = _fit_candidates(
        scene, rows, cols, st.final_yaw_starts, st.final_refine_starts, st.final_iterations, inits
    )
    cost, rot, p = cost[:, 0], rot[:, 0], p[:, 0]  # (T', K, ...)
    pick = _viterbi_candidates(cost, rot, p, st.smooth_weight, scene.body_height)
    for _ in range(st.smooth_rounds if tv > 1 else 0):
        chosen_r, chosen_p = rot[rows, pick], p[rows, pick]
        near = torch.stack([(rows - 1).clamp(min=0), (rows + 1).clamp(max=tv - 1)], 1)
        scene.fits += 2 * tv
        c_n, r_n, p_n = _refine_from(
            scene, rows, cols, chosen_r[near][:, None], chosen_p[near][:, None], st.final_iterations
        )
        cost = torch.cat([cost, c_n[:, 0]], 1)
        rot = torch.cat([rot, r_n[:, 0]], 1)
        p = torch.cat([p, p_n[:, 0]], 1)
        pick = _viterbi_candidates(cost, rot, p, st.smooth_weight, scene.body_height)
    return cost[rows, pick], rot[rows, pick], p[rows, pick]


def approximate_registration(
    reference: Reference,
    video: VideoFeatures,
    scale: float = 1.0,
    settings: Stage1Settings | None = None,
    generator: torch.Generator | None = None,
    progress: Callable[[str], None] | None = None,
) -> Stage1Result:
    """Stage 1: C by monotone coarse-to-fine alignment on pair fits, then T per video frame.

    The pair cost is :func:`fit_rigid_pairs`'s, each finer level warm-started per row from
    the nearest already evaluated row's best ``T``; costs are truncated (robust) and a slope
    prior around the frame-rate ratio ``reference.frame_rate / video.frame_rate`` is added,
    with steps ``0 <= C(t'+1) - C(t') <= ceil(step_factor * ratio)``. Only the coarse level
    and a band around its path are evaluated, never all ``T' x T`` pairs (unless the
    problem has at most ``settings.max_cells`` cells). Then ``T`` at ``(t', C(t'))`` with more
    starts and iterations, smoothed over time (see :class:`Stage1Settings`).

    Args:
        reference, video: the inputs; scale: G.
        settings: :class:`Stage1Settings`; generator: the silhouette subsample's draws.
        progress: called with a one-line message after each step.

    Returns:
        :class:`Stage1Result`.
    """
    start = time.perf_counter()
    st = _settings(settings)
    scene = _build_scene(reference, video, scale, st, _generator(generator))
    tv, tr = scene.num_video, scene.num_ref
    ratio = reference.frame_rate / video.frame_rate
    max_step = max(1, math.ceil(st.step_factor * ratio))
    radius = st.radius if st.radius is not None else max_step + st.factor
    dt = st.dtype
    best_cost = torch.full((tv,), math.inf, dtype=dt)
    best_rot = torch.eye(3, dtype=dt).repeat(tv, 1, 1)
    best_p = torch.zeros(tv, 3, dtype=dt)

    def cost_fn(rows: Tensor, cols: Tensor) -> Tensor:
        seen = torch.isfinite(best_cost).nonzero().flatten()
        inits = []
        if len(seen):
            pos = torch.searchsorted(seen, rows).clamp(max=len(seen) - 1)
            left = seen[(pos - 1).clamp(min=0)]
            right = seen[pos]
            near = torch.where((rows - left).abs() <= (right - rows).abs(), left, right)
            inits = [_as_pair_init((best_rot[near], best_p[near]), rows, cols, dt)]
        cost, rot, p = _fit_candidates(
            scene,
            rows,
            cols,
            st.yaw_starts,
            st.refine_starts,
            st.iterations,
            inits,
            _stride(cols, st),
        )
        fit = _best(cost, rot, p)
        k = fit.cost.argmin(-1)
        row_best = fit.cost.gather(-1, k[:, None])[:, 0]
        idx = torch.arange(len(rows))
        better = row_best < best_cost[rows]
        upd = rows[better]
        best_cost[upd] = row_best[better]
        best_rot[upd] = fit.rotation[idx, k][better]
        best_p[upd] = fit.translation[idx, k][better]
        if progress is not None:
            progress(f"stage 1: {cols.numel()} pairs ({scene.fits} pair fits so far)")
        return fit.cost.to(torch.get_default_dtype())

    slope_cost = slope_step_cost(max_step, ratio, st.slope_weight) if st.slope_weight else None
    try:
        alignment = coarse_to_fine_align(
            cost_fn,
            tv,
            tr,
            max_step,
            factor=st.factor,
            radius=radius,
            max_cells=st.max_cells,
            fix_start=st.fix_start,
            fix_end=st.fix_end,
            step_cost=slope_cost,
            robust=st.robust,
            robust_scale=st.robust_scale,
            beam=st.beam,
            prune=st.prune,
        )
    except AlignmentError as err:
        raise RegistrationError(f"stage 1 time alignment failed: {err}") from err
    c_path = alignment.path[0]
    row_init = (best_rot, best_p)
    cost, rot, p = _final_transforms(scene, c_path, row_init)
    if progress is not None:
        progress(f"stage 1: final T for {tv} frames")
    return Stage1Result(c_path, rot, p, cost, scene.fits, time.perf_counter() - start)
