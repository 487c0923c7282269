"""Choosing among independent searches by how well each explains the images.

Particle BP scores each part against the other parts' estimates (the occlusion-aware
``phi_j``); whether a whole posture explains an image is a different, joint question: render
it and compare. :func:`render_residual` does that -- pixels where the rendered silhouette and
the observed one disagree, plus (optionally) the colour difference of the part-coloured
rendering against the observed image -- and :func:`best_per_frame` keeps, frame by frame,
the posture of the search with the smallest residual (:func:`best_overall`: the one search
with the smallest residual over all frames, where frames are coupled and a posture mixed
from several searches would break what couples them). Several searches from the same start
with different random draws (a batch of particle BP runs) fall into different local optima
(a leg crossed over, an arm flipped); the joint residual tells them apart without the truth.

Shapes: ``S`` searches (a batch), ``T`` frames, ``C`` cameras, ``P`` parts, ``H x W``
images. Units: pixels (silhouette) and nats (the colour term is the intensity cue's
``|I - colour|^2 / (2 sigma^2)`` per pixel times its weight, so both read as a cost per pixel).
"""

from __future__ import annotations

import torch
from torch import Tensor

from motion.body.observation import Observation, PartShapes, body_layers
from motion.cameras import CameraRig
from motion.render import project_parts, render_intensity

__all__ = ["best_overall", "best_per_frame", "render_residual"]


def render_residual(
    shapes: PartShapes,
    rig: CameraRig,
    obs: Observation,
    poses: Tensor,
    colours: Tensor | None = None,
    colour_weight: float = 0.05,
    sigma: float = 0.1,
) -> Tensor:
    """The joint image residual of postures, summed over cameras.

    Args:
        shapes: the parts' capsules (P parts).
        rig: C cameras; obs: the observation of T frames (batch 1, shared).
        poses: ``(S, T, P, 7)`` part poses per search.
        colours: ``(P, 3)`` part colours in [0, 1] (``None``: silhouette only).
        colour_weight, sigma: the colour term, as :class:`motion.body.observation.Intensity`.

    Returns:
        ``(S, T)``: silhouette pixels in disagreement (both directions) plus the colour term
        over the rendered body's pixels (each against the colour of the part in front).
    """
    if poses.dim() != 4 or poses.shape[-1] != 7:
        raise ValueError(f"poses must have shape (S, T, P, 7); got {tuple(poses.shape)}")
    t_obs = obs.silhouette.shape[1]
    if poses.shape[1] != t_obs:
        raise ValueError(f"poses have {poses.shape[1]} frames; the observation has {t_obs}")
    h, w = obs.size
    segments = shapes.segments(poses, torch.arange(shapes.num_parts, device=poses.device))
    layers = body_layers(project_parts(rig, segments, shapes.radii.to(poses)), h, w)
    covered = (layers.label >= 0).to(poses.dtype)  # (S, T, C, H, W)
    observed = obs.silhouette[0].to(covered)
    residual = (covered - observed).abs().flatten(2).sum(-1)  # (S, T)
    if colours is not None and obs.image is not None:
        rendered = render_intensity(layers.label, colours.to(poses))  # (S, T, C, 3, H, W)
        diff = (rendered - obs.image[0].to(rendered)).square().sum(-3) * covered
        residual = residual + colour_weight * (diff / (2 * sigma**2)).flatten(2).sum(-1)
    return residual


def best_per_frame(poses: Tensor, residual: Tensor) -> tuple[Tensor, Tensor]:
    """Per frame, the posture of the search with the smallest residual.

    Shapes: poses ``(S, T, P, 7)``, residual ``(S, T)`` -> ``(T, P, 7)`` and the chosen
    search per frame ``(T,)`` long.
    """
    _check_residual(poses, residual)
    choice = residual.argmin(0)
    frames = torch.arange(poses.shape[1], device=poses.device)
    return poses[choice, frames], choice


def best_overall(poses: Tensor, residual: Tensor) -> tuple[Tensor, Tensor]:
    """The postures of the one search with the smallest residual summed over the frames.

    Shapes: poses ``(S, T, P, 7)``, residual ``(S, T)`` -> ``(T, P, 7)`` and the chosen
    search for every frame ``(T,)`` long (one value repeated).
    """
    _check_residual(poses, residual)
    best = residual.sum(1).argmin()
    return poses[best], best.expand(poses.shape[1]).clone()


def _check_residual(poses: Tensor, residual: Tensor) -> None:
    if residual.shape != poses.shape[:2]:
        raise ValueError(
            f"residual must have shape {tuple(poses.shape[:2])} (searches, frames); "
            f"got {tuple(residual.shape)}"
        )
