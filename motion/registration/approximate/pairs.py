"""The best rigid ``T`` of each pair (video frame ``t'``, reference frame ``t``):
:func:`fit_rigid_pairs` and :class:`PairFit`. Starts are screened by their cost, the best
refined by Levenberg-Marquardt (in a band of neighbouring reference frames only every
``anchor_stride``-th pair from all starts, the others from the anchors around them), and
candidates ranked by the image cost plus the heading prior.

The heading prior (``Stage1Settings.heading_weight``, :func:`_heading_penalty`) lives here
with the fits because each needs the other: the person's track it compares against comes from
rigid fits (:func:`_track_at`), and every fit ranks its starts and candidates with it.

Shapes: ``R`` rows (video frames of the pairs), ``W`` reference frames per row, ``K``
candidates per pair; rotations ``(..., 3, 3)`` (column vectors), translations ``(..., 3)``
metres, costs as :mod:`motion.registration.approximate.cost`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from motion.registration.approximate.cost import _Batch, _levenberg_marquardt
from motion.registration.approximate.scene import _build_scene, _check_pairs, _generator, _Scene
from motion.registration.approximate.settings import Stage1Settings, _settings
from motion.registration.approximate.starts import (
    Init,
    _as_pair_init,
    _keypoint_starts,
    _targets,
    _yaw_rotations,
)
from motion.registration.types import Reference, VideoFeatures


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


def _window(scene: _Scene, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The frames ``rows - k``, ``rows + k`` (clamped) that the person's velocity at ``rows``
    is measured between (``2k + 1`` frames ~ ``heading_window`` seconds), and their span in
    seconds."""
    k = max(1, round(scene.settings.heading_window * scene.video_rate / 2))
    lo = (rows - k).clamp(min=0)
    hi = (rows + k).clamp(max=scene.num_video - 1)
    return lo, hi, (hi - lo).clamp(min=1).to(scene.landmarks.dtype) / scene.video_rate


def _track_refs(scene: _Scene, frames: Tensor) -> Tensor:
    """The reference frames that the track at video ``frames (n,)`` is fitted against:
    ``settings.yaw_starts`` evenly spaced ones, ``(n, W)``."""
    refs = torch.linspace(0, scene.num_ref - 1, scene.settings.yaw_starts, device=scene.device)
    refs = refs.round().long().unique()
    return refs.expand(len(frames), -1)


def _fit_track(scene: _Scene, frames: Tensor, kp: Init | None) -> None:
    """Fit the person's track at video ``frames (n,)`` (unique) into ``scene.track``: the root
    position of the best rigid fit against :func:`_track_refs` (heading prior off; a
    mirror-image solution has nearly the same position), with keypoint starts ``kp``
    (:func:`_keypoint_starts` of those pairs)."""
    st = scene.settings
    refs = _track_refs(scene, frames)
    scene.fits += refs.numel()
    scene.tracking = True
    try:
        fit = _best(
            *_fit_all_starts(
                scene, frames, refs, st.yaw_starts, st.refine_starts, st.iterations, [], kp
            )
        )
    finally:
        scene.tracking = False
    k = fit.cost.argmin(-1)
    scene.track[frames] = fit.translation[torch.arange(len(frames), device=k.device), k]


def _untracked(scene: _Scene, frames: Tensor) -> Tensor:
    """Those of video ``frames`` whose track is not fitted yet, unique."""
    return frames[torch.isnan(scene.track[frames, 0])].unique()


def _track_at(scene: _Scene, frames: Tensor) -> Tensor:
    """The person's root position at video ``frames`` ``(n,)`` -> ``(n, 3)`` metres
    (:func:`_fit_track`), computed once per frame when first needed."""
    need = _untracked(scene, frames)
    if need.numel():
        _fit_track(scene, need, _keypoint_starts(scene, need, _track_refs(scene, need)))
    return scene.track[frames]


def _heading_penalty(scene: _Scene, rows: Tensor, cols: Tensor, rot: Tensor) -> Tensor:
    """The heading prior (``Stage1Settings.heading_weight``) of candidates ``rot (..., 3, 3)``
    for pairs ``rows``, ``cols`` (broadcast to ``rot``'s leading shape). ``(...)``."""
    st = scene.settings
    if scene.v_ref is None or scene.tracking:
        return torch.zeros(rot.shape[:-2], dtype=rot.dtype, device=rot.device)
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
            p0 = torch.zeros(nr, w, yaw_starts, 3, dtype=yaws.dtype, device=yaws.device)
            cost0 = torch.full((nr, w, yaw_starts), math.inf, dtype=yaws.dtype, device=yaws.device)
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
    # a start that is not a pose (the 2-D joints' solve gives NaN where they are degenerate)
    # is no candidate: it descends from its pair's first start instead (a finite pose: no
    # NaN pixel reaches the image reads, no NaN rotation the smoothness between frames'
    # candidates) and its cost is infinite (a NaN would win every argmin)
    void = ~(torch.isfinite(rot0).flatten(3).all(-1) & torch.isfinite(p0).all(-1))  # (R, W, K)
    if bool(void.any()):
        rot0 = torch.where(void[..., None, None], rot0[:, :, :1], rot0)
        p0 = torch.where(void[..., None], p0[:, :, :1], p0)
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
    cost = torch.cat(out_c).reshape(r, w, k).masked_fill(void, math.inf)
    return (
        cost,
        torch.cat(out_r).reshape(r, w, k, 3, 3),
        torch.cat(out_p).reshape(r, w, k, 3),
    )


def _keypoint_starts_tracked(scene: _Scene, rows: Tensor, cols: Tensor) -> Init | None:
    """:func:`_keypoint_starts` of pairs ``rows (R,)``, ``cols (R, W)``, after fitting the
    track (:func:`_fit_track`) at every frame that the heading prior of ``rows`` will read:
    in one batch here, rather than on demand chunk by chunk of the starts' screening (several
    small batches, each with its own keypoint solve and LM)."""
    if scene.v_ref is not None and not scene.tracking:
        lo, hi, _ = _window(scene, rows)
        need = _untracked(scene, torch.cat([lo, hi]))
        if need.numel():
            _fit_track(scene, need, _keypoint_starts(scene, need, _track_refs(scene, need)))
    return _keypoint_starts(scene, rows, cols)


def _fit_all_starts(
    scene: _Scene,
    rows: Tensor,
    cols: Tensor,
    yaw_starts: int,
    refine: int,
    iterations: int,
    inits: list[Init],
    kp: Init | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Every pair ``rows (R,)``, ``cols (R, W)`` refined from all its starts: the ``refine``
    best of ``yaw_starts`` screened upright starts, each warm start in ``inits`` and the
    keypoint start ``kp`` (``(R, W, 3, 3)``, ``(R, W, 3)``, or ``None``). Returns
    :func:`_fit_candidates`'s."""
    rot, p = _analytic_starts(scene, rows, cols, yaw_starts, refine)
    warm = [*inits, *([kp] if kp is not None else [])]  # each one more start per pair
    rots = torch.cat([rot, *(r[:, :, None] for r, _ in warm)], 2)
    ps = torch.cat([p, *(q[:, :, None] for _, q in warm)], 2)
    return _refine_from(scene, rows, cols, rots, ps, iterations)


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
        pos = torch.arange(anchor_stride // 2, w, anchor_stride, device=cols.device)
        a_inits = [(i[0][:, pos], i[1][:, pos]) for i in inits]
        fit = _best(
            *_fit_candidates(
                scene, rows, cols[:, pos], yaw_starts, refine, iterations, a_inits, count=False
            )
        )
        j = torch.arange(w, device=cols.device)
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
    kp = _keypoint_starts_tracked(scene, rows, cols)
    return _fit_all_starts(scene, rows, cols, yaw_starts, refine, iterations, inits, kp)


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
    scene = _build_scene(reference, video, scale, st, _generator(generator, video))
    rows, cols = _check_pairs(scene, rows, cols)
    inits = [] if init is None else [_as_pair_init(init, rows, cols, st.dtype)]
    cost, rot, p = _fit_candidates(
        scene, rows, cols, st.yaw_starts, st.refine_starts, st.iterations, inits, _stride(cols, st)
    )
    return _best(cost, rot, p)
