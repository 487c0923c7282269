"""Stages 2 and 3: T and A given C by particle BP on the spatiotemporal body graph, and C
refined through the same graph (the proposal's Section 6.2).

**Stage 2** (6.2.1): one SE(3) node per (video frame, body part), kinematic edges within a
frame (:class:`motion.body.graph.Connections`), temporal edges between a part and itself in
the next frame, the occlusion-aware observation factor of every camera
(:class:`motion.body.observation.BodyObservation`), and a pull of each part toward the
reference posture at C(t') placed by the current T (the articulation prior: as little change
to the reference as explains the video).

**Stage 3** (6.2.2): C joins the same graph as a chain of discrete nodes, one per video
frame, whose states are the reference frames of a band around the current C, with monotone
transitions (:class:`pgm.BandedMonotoneFactor`); each C node is coupled to its frame's part
nodes by :class:`pgm.LookupPose` -- state c pulls part p toward ``T(t') B_{c, p}`` -- which
replaces stage 2's fixed prior. One :func:`pgm.particle_bp` run passes messages between the
chain and the parts (hybrid messages): the parts see a mixture over the band of reference
postures, the chain sees how well each reference frame's posture agrees with the parts'
particles. Between runs the posture is fitted to the skeleton (T and A), the band is
re-centred on the new C, and the rounds stop when C stops changing. Last, C is chosen once
more over the whole video with a tempo (:func:`_tempo_c`): the chain inside BP is first
order, and a performer's tempo changes slowly.

Long videos are cut into windows with overlap (memory stays bounded, cost grows linearly);
each frame keeps the estimate of the window in which it lies farthest from an edge.

Units: metres, radians; frames are 0-based indices. Shapes: ``T'`` video frames, ``P``
parts, ``J`` joints, ``K`` particles, ``W`` band states.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import ClassVar

import torch
from kornia.geometry.conversions import rotation_matrix_to_quaternion
from torch import Tensor

from motion.alignment import TempoPrior, slope_step_cost, tempo_align
from motion.body.fit import fit_part_rotations, fit_posture, rigid_fit
from motion.body.graph import Connections, PosturePrior, Temporal, relative_rotations
from motion.body.observation import (
    BodyObservation,
    Edges,
    Intensity,
    Joints2D,
    PartShapes,
    Silhouette,
    body_layers,
)
from motion.body.solve import Images, PostureSettings, solve_posture
from motion.body.spec import BodySpec
from motion.registration.types import (
    FRAME_CHUNK,
    Reference,
    RegistrationError,
    VideoFeatures,
    frame_ranges,
    nonfinite_frames,
    scaled_spec,
)
from motion.render import project_parts
from motion.settings import SettingError, Settings, setting
from motion.smoothing import smooth_rotations, smooth_values
from pgm import (
    SE3,
    BandedMonotoneFactor,
    Discrete,
    Geometric,
    LookupPose,
    ParticleGraph,
    RigidConnection,
    SpatioTemporalTemplate,
)
from pgm.rotations import qconj, qmul, qrotate

__all__ = [
    "RefineResult",
    "RefineSettings",
    "RefineSettingsError",
    "colour_image",
    "estimate_part_colours",
    "part_keypoints",
    "place_poses",
    "refine",
    "smooth_posture",
]

Progress = Callable[[Iterable, str, int], Iterator]


class RefineSettingsError(SettingError, RegistrationError):
    """A stage 2-3 setting outside its type or range, or settings that do not fit together
    (a :class:`RegistrationError` too)."""


def _default_connection() -> Connections:
    return Connections(0.02, 1.0, Geometric(1.0, 0.25, 5))


@dataclass(frozen=True)
class RefineSettings(Settings):
    """Every tuning constant of stages 2 and 3, in one place (each field with its range and
    meaning, :func:`motion.settings.setting`; checked when built, a bad value raising
    :class:`RefineSettingsError`).

    Why four of the defaults are on (their measured effects:
    docs/decisions/004-tuning-evidence.md): the heavy-tailed articulation prior
    (``articulation_outlier``) lets a few joints differ a lot, as a student's do, where a
    Gaussian one pulls every joint a little; ``reanchor`` stops stage 1's T errors from
    persisting through the rounds; the tempo alignment (``tempo_std``) stops C wandering
    where the images hardly tell frames apart; the smoothing (``smooth_s``) removes the
    particles' frame-to-frame sampling noise from A and T.

    Checked together: ``overlap < window``; ``articulation_outlier_std >
    articulation_std`` where ``articulation_outlier`` is not 0; with ``refine_c``, C's band
    of ``2 * band + 1`` states fits in the ``particles``.
    """

    setting_error: ClassVar[type[SettingError]] = RefineSettingsError

    particles: int = setting(100, "K, particles per part", ge=2)
    iterations: int = setting(5, "particle BP passes (the proposal runs 6 iterations twice)", ge=1)
    restarts: int = setting(2, "particle BP restarts (with iterations: its passes)", ge=1)
    searches: int = setting(
        1,
        "independent particle BP searches per window (a batch of runs with different draws); "
        "with more than one the window keeps the search whose rendering explains its frames "
        "best in sum (motion.body.solve, choose=all: one search for the whole window, so the "
        "temporal edges and C's chain stay whole), at about searches times the cost",
        ge=1,
    )
    window: int = setting(24, "video frames per window", ge=1)
    overlap: int = setting(4, "video frames shared between neighbouring windows", ge=0)
    prior_pos_std: float = setting(
        0.08,
        "metres, the articulation prior's position spread; broad, so that the images decide "
        "the articulation where they can",
        gt=0,
    )
    prior_rot_std: float = setting(
        0.5, "radians, the articulation prior's rotation spread (broad, as prior_pos_std)", gt=0
    )
    connection: Connections = setting(
        default_factory=_default_connection,
        doc="the kinematic edges' position spread and schedules (see Connections; its rot_std "
        "and rel_rot are replaced by the articulation prior's)",
        opaque=True,
    )
    articulation_std: float = setting(
        0.05,
        "radians, the spread of each joint's rotation about the reference's at C(t') (the "
        "articulation prior E_A on the kinematic edges), the core of the heavy-tailed prior",
        gt=0,
    )
    articulation_outlier: float = setting(
        0.1,
        "a heavy-tailed E_A: each joint's rotation kernel is the mixture (1 - w) "
        "k(articulation_std) + w k(articulation_outlier_std) (pgm.RigidConnection's outlier), "
        "and the posture fit pulls each joint by its share of that mixture; a student differs "
        "from the reference in a few joints by a lot more often than in every joint a little "
        "(0: a Gaussian E_A)",
        ge=0,
        lt=1,
    )
    articulation_outlier_std: float = setting(
        0.5,
        "radians, the spread of the heavy-tailed E_A's outlier kernel (must exceed "
        "articulation_std)",
        gt=0,
    )
    twist_from_reference: bool = setting(
        True,
        "fit each part's rotation to its axis and its children's joints, the rest (a limb's "
        "twist) from the reference (motion.body.fit.fit_part_rotations); false: BP's "
        "rotations as they are",
    )
    landmark_std: float = setting(
        0.03,
        "metres, how far BP's part ends typically land from the truth (what the posture fit "
        "weighs them by against the articulation prior)",
        gt=0,
    )
    whole_body_t: bool = setting(
        True,
        "T's rotation from the whole body (the reference posture at C fitted rigidly to every "
        "estimated landmark), not from the root part alone (a pelvis is too small to orient "
        "well); needs twist_from_reference",
    )
    temporal: Temporal | None = setting(
        default_factory=Temporal,
        doc="temporal edges (none: frames independent)",
        opaque=True,
    )
    silhouette: float = setting(
        1.0, "weight of the silhouette cue, nats per pixel (0 leaves it out)", ge=0
    )
    edges: float = setting(0.2, "weight of the edges cue, nats per pixel (0 leaves it out)", ge=0)
    intensity: float = setting(
        0.05, "weight of the intensity cue, nats per pixel (0 leaves it out)", ge=0
    )
    joints: float = setting(
        1.0, "weight of the 2-D joints cue, nats per joint (0 leaves it out)", ge=0
    )
    joints_sigma: float = setting(4.0, "pixels, the 2-D joints cue's Cauchy scale", gt=0)
    kernel_scale: tuple[float, float] = setting(
        (0.02, 0.5), "the proposal kernels' spreads (metres, radians)", gt=0
    )
    kernel_end: float = setting(
        0.05, "the proposal kernels' final multiplier (annealed geometrically)", gt=0
    )
    refine_c: bool = setting(True, "run stage 3 (C through the chain) after stage 2")
    rounds: int = setting(
        3, "at most this many stage 3 rounds (each one particle BP run per window)", ge=0
    )
    band: int = setting(12, "half-width of C's band, reference frames", ge=0)
    couple_pos_std: float = setting(
        0.04, "metres, the coupling's position spread (as the prior's)", gt=0
    )
    couple_rot_std: float = setting(
        0.25, "radians, the coupling's rotation spread (as the prior's)", gt=0
    )
    max_step_factor: float = setting(
        2.5, "C's largest step is this times the frame-rate ratio", gt=0
    )
    reanchor: bool = setting(
        True,
        "place the next round's reference postures by the T fitted to this round's estimate "
        "(false: by the start T throughout, which leaves stage 1's T errors in place)",
    )
    slope_weight: float = setting(
        1.0,
        "nats of C's slope prior, w ((s - ratio) / ratio)^2 for a step of s reference frames "
        "(motion.alignment.slope_step_cost)",
        ge=0,
    )
    tempo_std: float = setting(
        0.3,
        "after the stage 3 rounds, C is chosen once more over the whole video, jointly with "
        "the student's tempo, by exact dynamic programming (motion.alignment.tempo_align): "
        "each reference frame in a band of tempo_band either side of stage 3's C is scored by "
        "the coupling's log-potential (pgm.LookupPose, spreads couple_*) of BP's part "
        "estimates against the reference posture there, each part weighted by how much of it "
        "the cameras see (a part out of view is estimated from the priors, i.e. from the last "
        "round's C); the prior is the slope prior on the tempo and a random walk of the tempo "
        "of tempo_std (relative) per square-root second (0.3: about 30 % in a second). Stage "
        "3's chain inside BP is first order, so each frame's step is chosen on its own: where "
        "the images hardly tell frames apart C wanders (a few frames either way through a "
        "walk) and at the ends it stalls. 0 switches it off",
        ge=0,
    )
    tempo_band: int = setting(
        24, "half-width of the tempo alignment's band (tempo_std), reference frames", ge=0
    )
    tempo_placement: str = setting(
        "registered",
        "where the tempo alignment (tempo_std) places each candidate reference posture before "
        "scoring BP's part estimates against it: registered (by the registration's T) or "
        "fitted (by the rigid motion that takes its parts' ends nearest the estimates' in "
        "least squares, the parts weighted as the cameras see them: the posture compared "
        "free of T's error, as the truth of another performer's C compares postures; "
        "measured on other performers, C moved by 0.3 frames at most: "
        "docs/results/register_cross_tempo.md)",
        choices=("registered", "fitted"),
    )
    smooth_s: float = setting(
        0.1,
        "seconds, the standard deviation of a Gaussian in time by which the final "
        "articulation A (each joint's rotation relative to the reference's at C), T's "
        "rotation (relative to the reference root's at C, so the reference's own pelvis swing "
        "is kept) and T's translation are smoothed (motion.smoothing, a local linear fit: the "
        "ends keep their trend); 0 leaves each frame's "
        "particle BP estimate as it is. Each window and frame is solved with a finite set of "
        "particles, so its posture carries a few degrees of sampling noise from frame to frame "
        "that the student's movement does not have; 0.1 s keeps changes slower than about 2 Hz "
        "(the kernel's -3 dB point is 0.19 / smooth_s Hz) -- the reference carries the "
        "movement's fast part",
        ge=0,
    )

    def validate(self) -> None:
        """Check (and normalise) every field, then the checks across fields (see the class
        docstring)."""
        super().validate()
        name = type(self).__name__
        if not self.overlap < self.window:
            raise RefineSettingsError(
                f"{name}: overlap must be in [0, window); got overlap={self.overlap}, "
                f"window={self.window}"
            )
        if self.articulation_outlier and not (
            self.articulation_outlier_std > self.articulation_std
        ):
            raise RefineSettingsError(
                f"{name}: articulation_outlier_std must exceed articulation_std; got "
                f"{self.articulation_outlier_std} <= {self.articulation_std}"
            )
        if self.refine_c and 2 * self.band + 1 > self.particles:
            raise RefineSettingsError(
                f"{name}: C's band of 2 * {self.band} + 1 states must fit in the "
                f"{self.particles} particles (a discrete node's states share the particle axis)"
            )


@dataclass
class RefineResult:
    """Stages 2-3 output. poses: ``(T', P, 7)`` part poses of the skeleton posture
    (``rotations`` placed at ``translation``: what is exported and drawn); C: ``(T',)`` long;
    rotations: ``(T', J, 3, 3)`` local (root's = T's rotation); translation: ``(T', 3)``
    root position, metres; rounds: stage 3 rounds run; c_changes: frames whose C changed in
    each round; particle_poses: ``(T', P, 7)`` particle BP's own estimate of each part
    (free parts, before the skeleton fit and the smoothing), for diagnostics;
    part_spread_deg: ``(T', P)`` how far each part's final particle marginal lets its
    orientation go (:func:`rotation_spread_deg`, the last round's; NaN where BP found no
    finite posture); warnings: sentences naming frames where BP found no finite posture
    (they keep their start)."""

    poses: Tensor
    C: Tensor
    rotations: Tensor
    translation: Tensor
    rounds: int
    c_changes: list[int]
    particle_poses: Tensor
    part_spread_deg: Tensor
    warnings: list[str] = field(default_factory=list)


# -- geometry helpers -----------------------------------------------------------------------
def place_poses(rotation: Tensor, translation: Tensor, poses: Tensor) -> Tensor:
    """``T`` applied to part poses in the root's frame: ``(..., 3, 3)``, ``(..., 3)``,
    ``(..., P, 7)`` -> ``(..., P, 7)`` (positions rotated and moved, frames rotated)."""
    q = rotation_matrix_to_quaternion(rotation.contiguous()).to(poses)  # (..., 4) w first
    pos = (rotation.to(poses)[..., None, :, :] @ poses[..., :3, None]).squeeze(-1)
    pos = pos + translation.to(poses)[..., None, :]
    quat = qmul(q[..., None, :].expand_as(poses[..., 3:7]), poses[..., 3:7])
    return torch.cat([pos, quat], -1)


def part_keypoints(reference: Reference, keypoint_joints: list[str] | None) -> Tensor | None:
    """``(P, 2)`` long: the keypoint column at each part's proximal and distal landmark
    (-1: none), for :class:`motion.body.observation.Joints2D`. A landmark is matched when
    the body model places it on exactly one skeleton joint that has a keypoint column."""
    if keypoint_joints is None:
        return None
    column = {name: i for i, name in enumerate(keypoint_joints)}
    model, spec = reference.model, reference.spec
    out = torch.full((spec.num_parts, 2), -1, dtype=torch.long, device="cpu")
    for p in range(spec.num_parts):
        for end, role in enumerate((spec.from_roles[p], spec.to_roles[p])):
            names = model.mapping[model.roles[int(role)]]
            if len(names) == 1 and names[0] in column:
                out[p, end] = column[names[0]]
    # built on the host, entry by entry; the cue reads it beside the data
    return out.to(reference.rotations.device) if (out >= 0).any() else None


def colour_image(image: Tensor | None) -> Tensor | None:
    """Colour frames as the cues read them, float in [0, 1]: uint8 frames (0-255, as
    :func:`motion.registration.inputs.features_from_sequence` can keep them, a quarter of
    the memory of float32) divided by 255; float images as they are."""
    if image is None or image.dtype != torch.uint8:
        return image
    return image.float() / 255


def estimate_part_colours(
    shapes: PartShapes, video: VideoFeatures, poses: Tensor, chunk: int = FRAME_CHUNK
) -> Tensor:
    """Each part's colour: the median of the image where the rendered posture shows that
    part in front and the silhouette agrees, over every frame and camera -- the student's
    appearance learnt from the current estimate. ``poses`` ``(T', P, 7)`` -> ``(P, 3)`` in
    [0, 1]; a part never seen gets the median colour of the whole silhouette. The images
    may be uint8 (:func:`colour_image`); rendered ``chunk`` frames at a time (the medians
    are over the same pixels as all at once)."""
    obs = video.observation
    if obs.image is None:
        raise RegistrationError(f"{video.name}: no colour images to learn part colours from")
    h, w = obs.size
    parts = torch.arange(shapes.num_parts, device=poses.device)
    whole: list[Tensor] = []  # colours (N, 3) of the silhouette's pixels, chunk by chunk
    per_part: list[list[Tensor]] = [[] for _ in range(shapes.num_parts)]
    for lo in range(0, poses.shape[0], chunk):
        sl = slice(lo, min(lo + chunk, poses.shape[0]))
        pose = poses[sl]
        segments = shapes.segments(pose, parts)
        label = body_layers(
            project_parts(video.cameras, segments, shapes.radii.to(pose)), h, w
        ).label  # (n, C, H, W)
        image = colour_image(obs.image[0, sl]).permute(0, 1, 3, 4, 2)  # (n, C, H, W, 3)
        on = obs.silhouette[0, sl] > 0.5
        whole.append(image[on])
        for p in range(shapes.num_parts):  # a loop over 15 parts, not over pixels
            per_part[p].append(image[(label == p) & on])
    silhouette = torch.cat(whole)
    median = (
        silhouette.median(0).values
        if len(silhouette)
        else torch.full((3,), 0.5, device=poses.device)
    )
    out = median.expand(shapes.num_parts, 3).clone()
    for p, pixels in enumerate(per_part):
        pixels = torch.cat(pixels)
        if len(pixels) >= 10:
            out[p] = pixels.median(0).values
    return out


def _window_starts(frames: int, window: int, overlap: int) -> list[int]:
    if frames <= window:
        return [0]
    step = window - overlap
    starts = [*range(0, frames - window, step), frames - window]
    return sorted(set(starts))


def _owner(frames: int, starts: list[int], window: int, device: torch.device) -> Tensor:
    """``(T',)`` which window each frame takes its estimate from: the one in which it lies
    farthest from an edge (on ``device``)."""
    t = torch.arange(frames, device=device)
    best = torch.full((frames,), -1.0, device=device)
    owner = torch.zeros(frames, dtype=torch.long, device=device)
    for i, s in enumerate(starts):
        inside = (t >= s) & (t < s + window)
        margin = torch.minimum(t - s, s + window - 1 - t).float()
        better = inside & (margin > best)
        owner[better], best[better] = i, margin[better]
    return owner


# -- the engine ------------------------------------------------------------------------------
@dataclass
class _Problem:
    """What every window shares."""

    reference: Reference
    video: VideoFeatures
    scale: float
    settings: RefineSettings
    spec: BodySpec  # the reference's body at the video's scale G
    shapes: PartShapes
    cues: list
    colours: Tensor | None  # (P, 3) the intensity cue's part colours (None: no colour)
    body: Tensor  # (T, P, 7) reference part poses in the root frame (float32, scaled)
    max_step: int
    step_log_potential: Tensor  # (max_step + 1,) C's slope prior
    connection_offsets: Tensor  # (E, 3) each joint in its parent part's frame, metres


def _cues(reference: Reference, video: VideoFeatures, settings: RefineSettings, colours):
    obs = video.observation
    cues = []
    if settings.silhouette > 0:
        cues.append(Silhouette(settings.silhouette, settings.silhouette))
    if settings.edges > 0 and obs.edge_distance is not None:
        cues.append(Edges(settings.edges))
    if settings.intensity > 0 and colours is not None:
        cues.append(Intensity(colours, settings.intensity))
    keys = part_keypoints(reference, video.keypoint_joints)
    if settings.joints > 0 and keys is not None and obs.keypoints is not None:
        cues.append(Joints2D(keys, settings.joints, settings.joints_sigma))
    if not cues:
        raise RegistrationError("every observation cue is switched off or has no input")
    return cues


def _run_window(
    problem: _Problem,
    frames: slice,
    c: Tensor,
    rotation: Tensor,
    translation: Tensor,
    couple: bool,
    generator: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor]:
    """One particle BP run over a window (:func:`motion.body.solve.solve_posture` on the
    window's graph). Returns part poses ``(n, P, 7)``, C ``(n,)``
    (unchanged without ``couple``) and each part's orientation spread ``(n, P)`` degrees
    (:func:`rotation_spread_deg`)."""
    s = problem.settings
    spec = problem.reference.spec
    p = spec.num_parts
    n = frames.stop - frames.start
    obs = problem.video.cut(frames).observation
    if obs.image is not None and obs.image.dtype == torch.uint8:  # the window's colour only
        obs = dataclasses.replace(obs, image=colour_image(obs.image))
    unary = BodyObservation(problem.shapes, problem.video.cameras, obs, cues=problem.cues)
    template = SpatioTemporalTemplate(
        p, temporal=None if s.temporal is None else s.temporal.factor()
    )
    pairwise = [_kinematic_edges(problem, problem.body[c]), *template.build(n)]
    v_body = n * p
    body_nodes = torch.arange(v_body, device="cpu")  # graph structure: on the CPU
    spaces = [(SE3(), body_nodes)]
    unaries = [(body_nodes, unary)]
    if couple:
        width = 2 * s.band + 1
        last = problem.body.shape[0] - 1
        offsets = (c - s.band).clamp(0, max(0, last + 1 - width))
        states = (offsets[:, None] + torch.arange(width, device=offsets.device)).clamp(
            max=last
        )  # (n, W)
        targets = place_poses(
            rotation[:, None], translation[:, None], problem.body[states]
        )  # (n, W, P, 7)
        chain_nodes = v_body + torch.arange(n, device="cpu")
        spaces.append((Discrete(width), chain_nodes))
        if n > 1:
            chain = torch.stack([chain_nodes[:-1], chain_nodes[1:]], 1)
            factor = BandedMonotoneFactor(problem.max_step, offsets, problem.step_log_potential)
            pairwise.append((chain, factor))
        edges = torch.stack([chain_nodes.repeat_interleave(p), body_nodes], 1)
        per_edge = targets.permute(0, 2, 1, 3).reshape(v_body, width, 7)
        pairwise.append((edges, LookupPose(per_edge, s.couple_pos_std, s.couple_rot_std)))
        start = place_poses(rotation, translation, problem.body[c])
    else:
        start = place_poses(rotation, translation, problem.body[c])  # (n, P, 7)
        unaries.append((body_nodes, PosturePrior(start, s.prior_pos_std, s.prior_rot_std)))
    graph = ParticleGraph(v_body + (n if couple else 0), spaces, pairwise, unaries)
    images = None
    if s.searches > 1:
        images = Images(problem.spec, problem.video.cameras, obs, problem.colours, s.intensity)
    solution = solve_posture(graph, start, _posture_settings(s), generator, images)
    result, poses = solution.result, solution.poses
    kept = int(solution.choice[0])  # one search for the whole window (choose="all")
    spread = rotation_spread_deg(
        result.particles[kept, :v_body],
        result.log_weights[kept, :v_body],
        result.best[kept, :v_body],
    ).reshape(n, p)
    if not couple:
        return poses, c, spread
    chosen = result.best[kept, v_body:, 0].round().long()
    return poses, states.gather(1, chosen[:, None]).squeeze(1), spread


def _posture_settings(settings: RefineSettings) -> PostureSettings:
    """The posture solver's settings of one window: its searches chosen among for the whole
    window, no polish (registration fits and polishes the skeleton itself), the rest
    :class:`PostureSettings`' defaults."""
    return PostureSettings(
        particles=settings.particles,
        iterations=settings.iterations,
        restarts=settings.restarts,
        searches=settings.searches,
        choose="all",
        kernel_scale=settings.kernel_scale,
        kernel_end=settings.kernel_end,
    )


def rotation_spread_deg(particles: Tensor, log_weights: Tensor, best: Tensor) -> Tensor:
    """The weighted RMS rotation angle of pose particles about the chosen one: how far a
    node's particle marginal lets its orientation go, the inference's own uncertainty of
    it (degrees).

    Args:
        particles: ``(..., K, 7)`` poses ``(x, y, z, qw, qx, qy, qz)``.
        log_weights: ``(..., K)`` normalised log marginal weights (``-inf``: none).
        best: ``(..., 7)`` the chosen pose.

    Returns:
        ``(...,)`` degrees; NaN where no particle has a finite weight.
    """
    cos = (particles[..., 3:] * best[..., None, 3:]).sum(-1).abs().clamp(max=1.0)
    angle = 2.0 * torch.acos(cos)  # (..., K) radians, q and -q alike
    finite = torch.isfinite(log_weights)
    weights = torch.softmax(torch.where(finite, log_weights, -torch.inf), -1)
    mean_square = (torch.where(finite, weights * angle**2, 0.0)).sum(-1)
    spread = torch.rad2deg(mean_square.sqrt())
    return torch.where(finite.any(-1), spread, torch.full_like(spread, math.nan))


def _kinematic_edges(problem: _Problem, reference: Tensor) -> tuple[Tensor, RigidConnection]:
    """The kinematic edges of every frame of a window, each joint's rotation kernel centred
    on the reference posture's relative rotation at C(t') (``reference`` ``(n, P, 7)``):
    the articulation prior ``E_A`` -- a joint pays for turning away from the reference,
    about every axis, including the twist about a limb's axis that no silhouette shows."""
    spec, c = problem.reference.spec, problem.settings.connection
    n, e = reference.shape[0], spec.edges.shape[0]
    # the graph's structure lives on the CPU (pgm's convention), its parameters with the data
    frames = torch.arange(n, device="cpu") * spec.num_parts
    edges = (spec.edges.cpu()[None] + frames[:, None, None]).reshape(-1, 2)
    offsets = problem.connection_offsets.repeat(n, 1)
    factor = RigidConnection(
        offsets,
        torch.zeros(3, device=offsets.device),
        c.pos_std,
        problem.settings.articulation_std,
        relative_rotations(spec, reference).reshape(n * e, 4).float(),
        schedule=c.schedule,
        rotation_schedule=c.rotation_schedule,
        outlier=problem.settings.articulation_outlier,
        outlier_rot_std=problem.settings.articulation_outlier_std,
    )
    return edges, factor


def _fit_weights(problem: _Problem, unit: Tensor, body: Tensor) -> float | Tensor:
    """The reference pull of :func:`fit_part_rotations` (m^2). Landmarks of std
    ``landmark_std`` against joint angles of std ``articulation_std`` weigh
    ``landmark_std^2 / (2 articulation_std^2)`` (MAP). With the heavy-tailed ``E_A`` each
    part's pull is its joint's mixture at the articulation BP found, one EM step of the
    scale mixture: ``landmark_std^2 (r / (2 s^2) + (1 - r) / (2 s_w^2))``, ``r`` the core's
    responsibility for the swing (the part's axis under BP's relative rotation, in the
    reference's; BP leaves the twist to chance), **smoothed in time** over ``smooth_s`` as a
    vector first -- a single frame's few degrees of particle noise must not release a joint,
    an articulation held over frames does. ``(T', P)`` or a float."""
    s, spec = problem.settings, problem.reference.spec
    core = s.landmark_std**2 / (2 * s.articulation_std**2)
    if not s.articulation_outlier:
        return core
    child = spec.edges[:, 1]
    axis = torch.nn.functional.normalize(spec.shapes.axis.to(unit)[child], dim=-1)
    axis = axis.expand(*unit.shape[:-2], -1, -1)  # (T', E, 3)
    rel = qmul(qconj(relative_rotations(spec, body.to(unit))), relative_rotations(spec, unit))
    dev = qrotate(rel, axis) - axis  # the swing's chord, in the reference joint's frame
    # a level, not a trend: nothing to extrapolate at the ends
    dev = smooth_values(dev, s.smooth_s * problem.video.frame_rate, fit="constant")
    swing = 2 * torch.asin((dev.norm(dim=-1) / 2).clamp(max=1.0))  # (T', E) radians
    narrow, wide = s.articulation_std, s.articulation_outlier_std
    # 2-D Gaussians of the swing: log N = -a^2 / (2 s^2) - 2 log s (+ a shared constant)
    log_core = math.log1p(-s.articulation_outlier) - swing**2 / (2 * narrow**2)
    log_tail = math.log(s.articulation_outlier) - swing**2 / (2 * wide**2)
    r = torch.sigmoid(log_core - log_tail + 2 * math.log(wide / narrow))
    weights = torch.full(
        (*unit.shape[:-2], spec.num_parts), core, dtype=unit.dtype, device=unit.device
    )
    weights[..., child] = s.landmark_std**2 * (r / (2 * narrow**2) + (1 - r) / (2 * wide**2))
    return weights


def _in_view(problem: _Problem, poses: Tensor) -> Tensor:
    """``(n, P)`` in [0, 1]: how much of each part the cameras see at ``poses`` ``(n, P,
    7)`` -- the share of its two ends inside some camera's image, in front of it. A part
    out of view is estimated from the priors alone (the last round's C), so its evidence
    about C is no evidence."""
    segments = problem.shapes.segments(
        poses, torch.arange(problem.shapes.num_parts, device=poses.device)
    )
    rig = problem.video.cameras
    uv, z = rig.project(segments.flatten(-3, -2))  # (n, C, 2P, 2), (n, C, 2P)
    size = rig.size.to(uv)[None, :, None, :]  # (1, C, 1, 2)
    inside = ((uv >= 0) & (uv < size)).all(-1) & (z > 0)
    share = inside.unflatten(-1, (-1, 2)).float().mean(-1)  # (n, C, P)
    return share.amax(1)


def _tempo_c(
    problem: _Problem, poses: Tensor, c: Tensor, rotation: Tensor, translation: Tensor
) -> Tensor:
    """C ``(T',)`` by :func:`motion.alignment.tempo_align` on the coupling's evidence: each
    reference frame in a band around ``c`` scored by :class:`pgm.LookupPose`'s log-potential
    of the part estimates ``poses`` ``(T', P, 7)`` against its posture placed by ``T``."""
    s = problem.settings
    ref_frames = problem.body.shape[0]
    width = min(2 * s.tempo_band + 1, ref_frames)
    offsets = (c - s.tempo_band).clamp(0, ref_frames - width)
    p = problem.reference.spec.num_parts
    cost = torch.empty(c.shape[0], width, dtype=torch.float64, device=c.device)
    for a in range(0, c.shape[0], FRAME_CHUNK):
        sl = slice(a, a + FRAME_CHUNK)
        states = offsets[sl, None] + torch.arange(width, device=offsets.device)  # (m, W)
        seen = _in_view(problem, poses[sl])  # (m, P)
        if s.tempo_placement == "fitted":
            targets = _fitted_postures(problem.spec, problem.body[states], poses[sl], seen)
        else:
            targets = place_poses(rotation[sl, None], translation[sl, None], problem.body[states])
        per_edge = targets.permute(0, 2, 1, 3).reshape(-1, width, 7)  # (m P, W, 7)
        coupling = LookupPose(per_edge, s.couple_pos_std, s.couple_rot_std)
        choice = torch.arange(width, dtype=poses.dtype, device=poses.device).expand(
            1, per_edge.shape[0], width
        )
        x = poses[sl].reshape(1, -1, 1, 7)
        lp = coupling.log_potential(slice(None), choice[..., None], x, width)  # (1, m P, W, 1)
        cost[sl] = -(lp[0, :, :, 0].reshape(-1, p, width) * seen[..., None]).sum(1).double()
    ratio = problem.reference.frame_rate / problem.video.frame_rate
    relative = s.tempo_std / math.sqrt(problem.video.frame_rate)  # per video frame
    prior = TempoPrior(ratio, s.slope_weight, relative)
    return tempo_align(cost, offsets, problem.max_step, prior).path[0].to(c.device)  # from the CPU


def _fitted_postures(spec: BodySpec, body: Tensor, estimates: Tensor, seen: Tensor) -> Tensor:
    """Each candidate posture ``body`` ``(m, W, P, 7)`` (part poses in the root's frame)
    placed by the rigid motion that takes its parts' ends nearest those of ``estimates``
    ``(m, P, 7)`` in least squares (:func:`motion.body.fit.rigid_fit`), each part weighted by
    ``seen`` ``(m, P)`` (a frame that sees no part weighs them all alike) -> ``(m, W, P, 7)``."""
    source = spec.landmarks(body.double()).flatten(-3, -2)  # (m, W, 2P, 3)
    target = spec.landmarks(estimates.double()).flatten(-3, -2)[:, None].expand_as(source)
    weight = seen.double().repeat_interleave(2, -1)  # (m, 2P): both ends of a part
    weight = torch.where(weight.sum(-1, keepdim=True) > 0, weight, torch.ones_like(weight))
    rotation, translation = rigid_fit(source, target, weight[:, None])
    return place_poses(rotation, translation, body.double()).to(body)


def _fit(problem: _Problem, poses: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """The skeleton posture of part poses: local rotations ``(T', J, 3, 3)`` and the root
    position ``(T', 3)``; joints no part drives keep the reference's rotations at C."""
    ref = problem.reference
    g = problem.scale
    unit = torch.cat([poses[..., :3].double() / g, poses[..., 3:].double()], -1)
    body = problem.body[c].double()
    body = torch.cat([body[..., :3] / g, body[..., 3:]], -1)  # B at C, unit size
    root = None
    observed = ref.spec.landmarks(unit)  # (T', P, 2, 3) the estimated part ends
    if problem.settings.whole_body_t:
        # T: the reference posture at C fitted rigidly to every estimated landmark
        flat = ref.spec.landmarks(body).flatten(-3, -2)
        root, _ = rigid_fit(flat, observed.flatten(-3, -2))
    if problem.settings.twist_from_reference:
        unit = fit_part_rotations(ref.spec, unit, body, _fit_weights(problem, unit, body), root)
    posture = fit_posture(ref.spec, ref.skeleton, ref.model, unit, ref.rotations[c])
    # fit_posture hangs the skeleton from the root part; with its rotations fixed, the
    # translation nearest (least squares) to every estimated landmark is that plus the mean
    # gap (the parts' ends drift a few cm along a chain of bones of fixed length)
    placed = ref.spec.poses(ref.model, ref.skeleton, posture.fk)  # (T', P, 7), unit size
    gap = observed - ref.spec.landmarks(placed)
    return posture.rotations, (posture.fk.positions[:, 0] + gap.mean((-3, -2))) * g


def _problem(
    reference: Reference, video: VideoFeatures, scale: float, settings: RefineSettings
) -> _Problem:
    """What every window shares, less the cues (they may need colours learnt at the start
    posture: set them after)."""
    spec = scaled_spec(reference.spec, scale)
    ratio = reference.frame_rate / video.frame_rate
    max_step = max(1, math.ceil(settings.max_step_factor * ratio))
    return _Problem(
        reference,
        video,
        float(scale),
        settings,
        spec,
        PartShapes(spec.shapes.axis.float(), spec.shapes.radii.float()),
        [],
        None,
        reference.body_poses(
            torch.arange(reference.num_frames, device=reference.rotations.device), scale
        ).float(),
        max_step,
        -slope_step_cost(max_step, ratio, settings.slope_weight).float(),
        spec.offsets[spec.edges[:, 1]].float(),
    )


def refine(
    reference: Reference,
    video: VideoFeatures,
    c: Tensor,
    rotation: Tensor,
    translation: Tensor,
    scale: float,
    settings: RefineSettings | None = None,
    generator: torch.Generator | None = None,
    colours: Tensor | None = None,
    progress: Progress | None = None,
) -> RefineResult:
    """Stages 2 (and 3): T, A (and C) from a start ``C`` ``(T',)`` long and root transforms
    ``rotation`` ``(T', 3, 3)``, ``translation`` ``(T', 3)`` metres (stage 1's), body scale
    ``scale`` (G). ``colours``: ``(P, 3)`` part colours for the intensity cue (``None``:
    learnt from the images at the start posture when the video has colour)."""
    s = settings or RefineSettings()
    g = generator or torch.Generator(device=rotation.device).manual_seed(0)
    t = video.num_frames
    if c.shape != (t,) or rotation.shape != (t, 3, 3) or translation.shape != (t, 3):
        raise RegistrationError(
            f"expected C ({t},), rotation ({t}, 3, 3), translation ({t}, 3); got "
            f"{tuple(c.shape)}, {tuple(rotation.shape)}, {tuple(translation.shape)}"
        )
    bad = nonfinite_frames(rotation, translation)
    if len(bad):
        raise RegistrationError(
            f"stages 2-3: the start transform T is NaN or infinite on video frames "
            f"{frame_ranges(bad)}; expected finite rotations and translations (stage 1's)"
        )
    problem = _problem(reference, video, scale, s)
    rotation, translation = rotation.float(), translation.float()
    c = c.to(rotation.device)  # C and T on the device of the data (stage 1's C is the CPU's)
    if colours is None and video.observation.image is not None and s.intensity > 0:
        start = place_poses(rotation, translation, problem.body[c])
        colours = estimate_part_colours(problem.shapes, video, start)
    problem.cues = _cues(reference, video, s, colours)
    problem.colours = colours if s.intensity > 0 else None
    starts = _window_starts(t, s.window, s.overlap)
    owner = _owner(t, starts, s.window, c.device)
    wrap = progress or (lambda items, desc, total: items)
    c = c.clone()
    poses = torch.zeros(t, reference.spec.num_parts, 7, device=c.device)
    spread = torch.full((t, reference.spec.num_parts), math.nan, device=c.device)
    changes: list[int] = []
    lost: set[int] = set()  # frames where BP found no finite posture
    rounds = 1 + (s.rounds if s.refine_c else 0)
    for r in range(rounds):
        couple = r > 0
        new_c = c.clone()
        label = "stage 2 (T, A)" if not couple else f"stage 3 (C) round {r}"
        for i in wrap(range(len(starts)), label, len(starts)):
            sl = slice(starts[i], min(t, starts[i] + s.window))
            est, c_win, sd = _run_window(
                problem, sl, c[sl], rotation[sl], translation[sl], couple, g
            )
            sd = torch.where(torch.isfinite(est).all(-1), sd, math.nan)  # lost: no marginal
            est, c_win = _keep_start_where_lost(
                problem, est, c_win, c[sl], rotation[sl], translation[sl], sl.start, lost
            )
            mine = owner[sl] == i
            poses[sl][mine] = est[mine]
            spread[sl][mine] = sd[mine].to(spread)
            new_c[sl][mine] = c_win[mine]
        if s.reanchor:
            local, root = _fit(problem, poses, new_c)
            rotation, translation = local[:, 0].float(), root.float()
        if couple:
            changes.append(int((new_c != c).sum()))
            c = torch.cummax(new_c, 0).values  # windows meet monotonically
            if changes[-1] == 0:
                break
    if s.refine_c and s.tempo_std > 0:
        c = _tempo_c(problem, poses, c, rotation, translation)
    local, root = _fit(problem, poses, c)
    if s.smooth_s > 0:
        local, root = smooth_posture(reference, c, local, root, s.smooth_s * video.frame_rate)
    skeleton = place_poses(local[:, 0], root, reference.posture_poses(local, scale)).to(poses)
    warnings = []
    if lost:
        warnings.append(
            f"video frames {frame_ranges(sorted(lost))} (counted from the first registered "
            "frame): particle BP found no finite posture there (every hypothesis of a part "
            "was impossible); they keep stage 1's posture"
        )
    return RefineResult(skeleton, c, local, root, rounds, changes, poses, spread, warnings)


def _keep_start_where_lost(
    problem: _Problem,
    est: Tensor,
    c_win: Tensor,
    c: Tensor,
    rotation: Tensor,
    translation: Tensor,
    first: int,
    lost: set[int],
) -> tuple[Tensor, Tensor]:
    """A window's frames whose estimate ``est`` ``(n, P, 7)`` is not finite take the start
    posture (``c``, ``T``) instead; their indices (``first`` + offset) are added to
    ``lost``."""
    bad = nonfinite_frames(est)
    if not len(bad):
        return est, c_win
    est, c_win = est.clone(), c_win.clone()
    est[bad] = place_poses(rotation[bad], translation[bad], problem.body[c[bad]]).to(est)
    c_win[bad] = c[bad]
    lost.update((bad + first).tolist())
    return est, c_win


def smooth_posture(
    reference: Reference, c: Tensor, rotations: Tensor, translation: Tensor, sigma: float
) -> tuple[Tensor, Tensor]:
    """A registered posture smoothed in time, in the reference's terms: each joint's
    articulation ``A = B_C^T R`` and the root's rotation relative to the reference root's
    at C (``T B_C,root^T``) smoothed as rotations, the root position as values, by a
    Gaussian of ``sigma`` video frames (:mod:`motion.smoothing`), each a local linear fit: a
    root moving through the video keeps its speed to the first and last frames, where a
    weighted mean would pull them toward the inside. ``c`` ``(T',)``,
    ``rotations`` ``(T', J, 3, 3)`` local, ``translation`` ``(T', 3)`` -> the same shapes;
    joints equal to the reference's at C stay so (to rounding)."""
    ref = reference.rotations[c].to(rotations)  # (T', J, 3, 3)
    articulation = ref.transpose(-1, -2) @ rotations
    heading = rotations[:, 0] @ ref[:, 0].transpose(-1, -2)
    out = ref @ smooth_rotations(articulation, sigma)
    out[:, 0] = smooth_rotations(heading, sigma) @ ref[:, 0]
    return out, smooth_values(translation, sigma)
