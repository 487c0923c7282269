"""One posture solver: start particles around a start posture, particle BP over a body
graph, the choice among independent searches and the gradient polish.

Registration's stages 2-3 (:mod:`motion.registration.refine`), the single-image experiments
(:mod:`experiments.nbp_single_image` and those built on it) and the body tests all solve a
posture the same way once their graph is built; :func:`solve_posture` is that sequence:

1. **Start**: every part node's K particles are the start pose moved by the SE(3) kernel
   (``start_spread``), in each of ``searches`` independent searches (a batch).
2. **Search**: :func:`pgm.particle_bp` under max-product (a posture is a maximum, not a
   marginal) with annealed proposal kernels.
3. **Choice** (``searches > 1``): per frame the search whose rendering explains the images
   best, or (``choose="all"``) the one search that explains all frames best
   (:mod:`motion.body.select`).
4. **Polish** (optional): gradient polish on the soft renderer (:mod:`motion.body.polish`).

Building the graph stays with the caller (registration couples C to the parts, the
experiments add joint limits or temporal edges, tests priors): the solver reads only that
the graph's first ``T * P`` nodes are the parts, frame-major (node ``t * P + p``), as
:func:`motion.body.graph.body_graph` and registration lay them out; nodes past them (a
discrete C chain) start at zero, their values being their states.

Every random draw is on the given generator, in a fixed order (the start perturbation, then
particle BP's), so a seed gives the same posture. Units: metres, radians. Shapes: ``S``
searches, ``T`` frames, ``P`` parts, ``V`` graph nodes, ``K`` particles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.body.observation import Observation, PartShapes
from motion.body.polish import polish
from motion.body.select import best_overall, best_per_frame, render_residual
from motion.body.spec import BodySpec
from motion.cameras import CameraRig
from motion.settings import Settings, setting
from pgm import SE3, Constant, Geometric, MaxSemiring, ParticleGraph, particle_bp
from pgm.particle_bp import PROPOSALS, ParticleResult
from pgm.schedules import Schedule

__all__ = ["Images", "PostureSettings", "PostureSolution", "anneal_schedule", "solve_posture"]


@dataclass(frozen=True)
class PostureSettings(Settings):
    """How :func:`solve_posture` searches (each field with its range and meaning; checked
    when built, a bad value raising :class:`motion.settings.SettingError` that names the
    field, what it must be and what it got)."""

    particles: int = setting(100, "K, particles per part", ge=2)
    iterations: int = setting(5, "particle BP passes per restart", ge=1)
    restarts: int = setting(
        2, "particle BP restarts: the annealing run again from the particles reached", ge=1
    )
    searches: int = setting(
        1,
        "independent searches (a batch of particle BP runs with different draws); with more "
        "than one, the one whose rendering explains the images best is kept (see choose)",
        ge=1,
    )
    choose: str = setting(
        "frame",
        "with several searches: frame (each frame keeps its best search) or all (every frame "
        "keeps the one search whose rendering explains the frames best in sum: where temporal "
        "edges or a chain couple the frames, a posture mixed from several searches would "
        "break them)",
        choices=("frame", "all"),
    )
    # K copies of the start would be one hypothesis (the first pass weights the initial
    # particles as they are); a small spread gives it K near the start to choose from, the
    # proposal kernels (kernel_scale) doing the wide search after.
    start_spread: tuple[float, float] = setting(
        (0.02, 0.1), "the start particles' spread about the start pose (metres, radians)", ge=0
    )
    kernel_scale: tuple[float, float] = setting(
        (0.02, 0.5), "the proposal kernels' spreads (metres, radians)", gt=0
    )
    kernel_end: float = setting(
        0.05, "the proposal kernels' final multiplier (annealed geometrically)", gt=0
    )
    annealing: bool = setting(
        True,
        "anneal the proposal kernels from 1 to kernel_end over the iterations (false: the "
        "geometric mean of that range throughout)",
    )
    proposal: str | None = setting(
        None,
        "particle proposal (mixture: neighbours propose through the connections; own: BPMC); "
        "none: the graph's",
        choices=PROPOSALS,
    )
    # 30 resampled centres keep the proposal density exact at a third less time per
    # iteration than all K = 150, for 0.1 cm more error (docs/benchmarks.md).
    proposal_centres: int | None = setting(
        30, "kernel centres per proposal component, at most K (none: all K particles)", ge=1
    )
    polish: bool = setting(
        False, "gradient polish of the chosen poses on the soft renderer (needs the images)"
    )


@dataclass(frozen=True)
class Images:
    """What the cameras saw, for choosing among searches and for the polish.

    Attributes:
        spec: the body (its parts' capsules and joints).
        rig: C cameras. observation: T frames (batch 1).
        colours: ``(P, 3)`` part colours in [0, 1] for the colour terms (``None``: the
            silhouette only).
        colour_weight: nats per pixel of the choice's colour term (the intensity cue's).
    """

    spec: BodySpec
    rig: CameraRig
    observation: Observation
    colours: Tensor | None = None
    colour_weight: float = 0.05

    @property
    def shapes(self) -> PartShapes:
        """The parts' capsules in float32, as the observation factors render them."""
        return PartShapes(self.spec.shapes.axis.float(), self.spec.shapes.radii.float())


@dataclass
class PostureSolution:
    """What :func:`solve_posture` found.

    Attributes:
        poses: ``(T, P, 7)`` the chosen (and polished) part poses, float32.
        choice: ``(T,)`` long, the search each frame kept (zeros with one search).
        searches: ``(S, T, P, 7)`` each search's best part poses.
        residual: ``(S, T)`` each search's render residual
            (:func:`motion.body.select.render_residual`), ``None`` with one search.
        result: particle BP's result over the whole graph (batch S): the part nodes'
            particles and log-weights, and any nodes past them (a C chain's states).
    """

    poses: Tensor
    choice: Tensor
    searches: Tensor
    residual: Tensor | None
    result: ParticleResult


def anneal_schedule(end: float, iterations: int, annealing: bool = True) -> Schedule:
    """A geometric schedule from 1 to ``end`` over ``iterations``, or (``annealing`` off)
    the geometric mean of that range throughout: the same average spread, not shrinking."""
    if annealing:
        return Geometric(1.0, end, iterations)
    return Constant(math.sqrt(end))


def solve_posture(
    graph: ParticleGraph,
    start: Tensor,
    settings: PostureSettings,
    generator: torch.Generator,
    images: Images | None = None,
) -> PostureSolution:
    """Solve the part poses of a body graph from a start posture.

    Args:
        graph: a body graph whose first ``T * P`` nodes are the parts (SE(3), frame-major);
            any nodes past them are discrete.
        start: ``(T, P, 7)`` start part poses ``(x, y, z, qw, qx, qy, qz)``, metres.
        settings: :class:`PostureSettings`.
        generator: source of every random draw (the start's, then particle BP's).
        images: what the cameras saw; needed by ``searches > 1`` (to choose) and ``polish``.

    Returns:
        :class:`PostureSolution`.

    Raises:
        ValueError: a start of the wrong shape, a graph whose first ``T * P`` nodes are not
            SE(3), or ``searches > 1`` / ``polish`` without images.
    """
    _check_images(settings, images)
    initial = _start_particles(graph, start, settings, generator)
    result = _search(graph, initial, settings, generator)
    t, p = start.shape[:2]
    searches = result.best[:, : t * p].reshape(settings.searches, t, p, 7)
    poses, choice, residual = _choose(searches, images, settings.choose)
    if settings.polish:
        poses = polish(images.spec, images.rig, images.observation, poses, images.colours)
    return PostureSolution(poses, choice, searches, residual, result)


def _check_images(settings: PostureSettings, images: Images | None) -> None:
    """Refuse a choice or polish with nothing to choose or polish by."""
    if images is not None:
        return
    if settings.searches > 1:
        raise ValueError(
            f"searches = {settings.searches} needs images to choose among them by; got none"
        )
    if settings.polish:
        raise ValueError("polish needs images to polish against; got none")


def _start_particles(
    graph: ParticleGraph, start: Tensor, settings: PostureSettings, generator: torch.Generator
) -> Tensor:
    """``(S, V, K, 7)`` float32 initial particles: every part node's K particles the start
    pose moved by the start spread (one draw over all searches), zeros past the parts."""
    body = _part_nodes(graph, start)
    s, k = settings.searches, settings.particles
    # float32: the body graphs' factors hold float32 parameters and render in it
    centres = start.reshape(1, body, 1, 7).expand(s, body, k, 7).float()
    initial = torch.zeros(s, graph.num_nodes, k, 7, device=start.device)
    initial[:, :body] = SE3().perturb(centres, settings.start_spread, generator)
    return initial


def _part_nodes(graph: ParticleGraph, start: Tensor) -> int:
    """``T * P``, having checked that ``start`` is ``(T, P, 7)`` and that the graph's first
    ``T * P`` nodes are SE(3)."""
    if start.dim() != 3 or start.shape[-1] != 7:
        raise ValueError(f"start must have shape (T, P, 7); got {tuple(start.shape)}")
    body = start.shape[0] * start.shape[1]
    if graph.num_nodes < body:
        raise ValueError(
            f"the graph must have at least T * P = {body} nodes (the parts); got {graph.num_nodes}"
        )
    groups = graph.space_of[:body].unique().tolist()
    kinds = [type(graph.spaces[g][0]).__name__ for g in groups]
    if any(not isinstance(graph.spaces[g][0], SE3) for g in groups):
        raise ValueError(f"the graph's first {body} nodes must be SE3; got {', '.join(kinds)}")
    return body


def _search(
    graph: ParticleGraph, initial: Tensor, settings: PostureSettings, generator: torch.Generator
) -> ParticleResult:
    """Particle max-product from ``initial`` ``(S, V, K, 7)``."""
    k = settings.particles
    centres = settings.proposal_centres
    return particle_bp(
        graph,
        initial,
        iterations=settings.iterations,
        restarts=settings.restarts,
        generator=generator,
        semiring=MaxSemiring(),  # a posture is the best explanation, not a marginal mean
        proposal=settings.proposal,
        kernel_scale=_kernel_scales(graph, settings),
        kernel_schedule=anneal_schedule(
            settings.kernel_end, settings.iterations, settings.annealing
        ),
        proposal_centres=None if centres is None else min(centres, k),
    )


def _kernel_scales(graph: ParticleGraph, settings: PostureSettings) -> list:
    """The proposal kernel of every space group, in ``graph.spaces``' order: the parts'
    spreads; ``None`` for a discrete group (a C chain proposes its states, no kernel)."""
    return [None if space.discrete else settings.kernel_scale for space, _ in graph.spaces]


def _choose(
    searches: Tensor, images: Images | None, choose: str
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Per frame (``choose="frame"``) or for all frames (``"all"``) the search with the
    smallest render residual: ``(S, T, P, 7)`` -> poses ``(T, P, 7)``, choice ``(T,)``
    long, residual ``(S, T)``. One search is its own choice, rendered nothing."""
    if searches.shape[0] == 1:
        choice = torch.zeros(searches.shape[1], dtype=torch.long, device=searches.device)
        return searches[0], choice, None
    residual = render_residual(
        images.shapes,
        images.rig,
        images.observation,
        searches,
        images.colours,
        images.colour_weight,
    )
    pick = best_per_frame if choose == "frame" else best_overall
    poses, choice = pick(searches, residual)
    return poses, choice, residual
