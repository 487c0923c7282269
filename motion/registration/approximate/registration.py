"""Stage 1's flow (:func:`approximate_registration`): the correspondence ``C`` by the
coarse-to-fine monotone chain aligner on pair fits, then ``T`` per video frame at
``(t', C(t'))`` with more starts, made consistent over time by a chain Viterbi over each
frame's candidates; :class:`Stage1Result`.

Shapes: ``T'`` video frames, ``T`` reference frames, ``K`` candidates per frame; rotations
``(..., 3, 3)`` (column vectors), translations ``(..., 3)`` metres, angles in radians.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.alignment import AlignmentError, coarse_to_fine_align, slope_step_cost
from motion.geometry import relative_angle
from motion.registration.approximate.pairs import _best, _fit_candidates, _refine_from, _stride
from motion.registration.approximate.scene import _build_scene, _generator, _Scene
from motion.registration.approximate.settings import Stage1Settings, _settings
from motion.registration.approximate.starts import Init, _as_pair_init
from motion.registration.types import Reference, RegistrationError, VideoFeatures
from pgm import TableFactor, chain_map


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
    # a dynamic programme over small tables: on the CPU, as the time alignments (decision 006)
    result = chain_map(-cost.double().cpu()[None], TableFactor(table.double().cpu()))
    return result.assignment[0].to(cost.device)


def fitted_tempo(c: Tensor) -> float | None:
    """The student's tempo in reference frames per video frame read off a correspondence
    ``c`` ``(T',)`` while it moves: C's advance between its held ends (the leading and
    trailing runs of C's first and last value) over the video frames in which it advances;
    ``None`` where it never does. Not C's mean slope: a stall that drops a cycle (what a
    second pass should undo) pulls the mean slope down. Meant for videos slower than the
    reference (several reference frames per video frame), where C advances on every frame."""
    c = c.detach().cpu()
    steps = c[1:] - c[:-1]
    moving = int((steps > 0).sum())
    return float(steps.sum()) / moving if moving else None


def _final_transforms(scene: _Scene, c_path: Tensor, row_init: Init | None):
    """``T`` per video frame at ``(t', C(t'))``: many starts, then exact temporal smoothing
    over each frame's candidates, then rounds of LM warm-started from the neighbours' chosen
    ``T`` (added as candidates, smoothed again). Returns cost ``(T',)``, rotation
    ``(T', 3, 3)`` and translation ``(T', 3)``."""
    st = dataclasses.replace(scene.settings, edge_weight=scene.settings.final_edge_weight)
    scene.settings = st  # the final fit's own edge weight (see Stage1Settings)
    tv = c_path.shape[0]
    c_path = c_path.to(scene.device)  # the time alignment's, from the CPU
    rows = torch.arange(tv, device=c_path.device)
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
    problem has at most ``settings.max_cells`` cells); with ``settings.tempo_weight`` a second
    pass has the slope prior around the tempo read off the first (:func:`fitted_tempo`). Then
    ``T`` at ``(t', C(t'))`` with more starts and iterations, smoothed over time (see
    :class:`Stage1Settings`).

    Args:
        reference, video: the inputs; scale: G.
        settings: :class:`Stage1Settings`; generator: the silhouette subsample's draws.
        progress: called with a one-line message after each step.

    Returns:
        :class:`Stage1Result`.
    """
    start = time.perf_counter()
    st = _settings(settings)
    scene = _build_scene(reference, video, scale, st, _generator(generator, video))
    tv, tr = scene.num_video, scene.num_ref
    ratio = reference.frame_rate / video.frame_rate
    max_step = max(1, math.ceil(st.step_factor * ratio))
    radius = st.radius if st.radius is not None else max_step + st.factor
    dt = st.dtype
    best_cost = torch.full((tv,), math.inf, dtype=dt, device=scene.device)
    best_rot = torch.eye(3, dtype=dt, device=scene.device).repeat(tv, 1, 1)
    best_p = torch.zeros(tv, 3, dtype=dt, device=scene.device)

    def cost_fn(rows: Tensor, cols: Tensor) -> Tensor:
        # the time alignment asks from the CPU (motion.alignment): the fits run on the scene's
        rows, cols = rows.to(scene.device), cols.to(scene.device)
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
        idx = torch.arange(len(rows), device=rows.device)
        better = row_best < best_cost[rows]
        upd = rows[better]
        best_cost[upd] = row_best[better]
        best_rot[upd] = fit.rotation[idx, k][better]
        best_p[upd] = fit.translation[idx, k][better]
        if progress is not None:
            progress(f"stage 1: {cols.numel()} pairs ({scene.fits} pair fits so far)")
        return fit.cost.to(torch.get_default_dtype())

    def align(step_cost: Tensor | None):
        try:
            return coarse_to_fine_align(
                cost_fn,
                tv,
                tr,
                max_step,
                factor=st.factor,
                radius=radius,
                max_cells=st.max_cells,
                fix_start=st.fix_start,
                fix_end=st.fix_end,
                step_cost=step_cost,
                robust=st.robust,
                robust_scale=st.robust_scale,
                beam=st.beam,
                prune=st.prune,
            )
        except AlignmentError as err:
            raise RegistrationError(f"stage 1 time alignment failed: {err}") from err

    slope_cost = slope_step_cost(max_step, ratio, st.slope_weight) if st.slope_weight else None
    alignment = align(slope_cost)
    if st.tempo_weight > 0:
        tempo = fitted_tempo(alignment.path[0])
        if tempo is not None:
            tempo = min(max(tempo, ratio / st.step_factor), float(max_step))
            alignment = align(slope_step_cost(max_step, tempo, st.tempo_weight))
    c_path = alignment.path[0]
    row_init = (best_rot, best_p)
    cost, rot, p = _final_transforms(scene, c_path, row_init)
    if progress is not None:
        progress(f"stage 1: final T for {tv} frames")
    return Stage1Result(c_path, rot, p, cost, scene.fits, time.perf_counter() - start)
