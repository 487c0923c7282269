"""The registration pipeline: a 3-D reference against a video, stages 0-3 in order.

``register(reference, video)`` -> :class:`~motion.registration.types.Registration`:

* stage 0 -- the cameras, as given (``video.cameras``, or ``cameras``; ``motion register``
  checks a calibration with :func:`~motion.registration.cameras.initialise_cameras`, or gives
  one video without one a nominal field of view,
  :data:`~motion.registration.video.FIELD_OF_VIEW_DEG`; the routes from 2D-3D
  correspondences in :mod:`motion.registration.cameras` are for library users who have them,
  not used by the command), and the body scale G
  (:func:`~motion.registration.approximate.estimate_body_scale`, or given);
* stage 1 -- approximate registration: per candidate pair the best rigid T, then C by the
  monotone chain, coarse to fine (:func:`~motion.registration.approximate.
  approximate_registration`);
* stages 2-3 -- T and A by particle BP on the spatiotemporal body graph, alternating with C
  through the same graph (:func:`~motion.registration.refine.refine`);
* the posture polish -- T and A moved on the skeleton by gradient descent against the
  silhouettes and 2-D joints (:func:`~motion.registration.polish.polish_posture`).

Every stage is a function with typed inputs and outputs; this module only runs them in order,
times them and assembles the result. Deterministic under ``settings.seed``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from motion.body.observation import PartShapes, body_layers
from motion.cameras import CameraRig
from motion.devices import DeviceError, resolve_device, to_device
from motion.registration.approximate import (
    BodyScale,
    Stage1Result,
    Stage1Settings,
    approximate_registration,
    estimate_body_scale,
)
from motion.registration.polish import PosturePolishSettings, polish_posture
from motion.registration.refine import Progress, RefineSettings, place_poses, refine
from motion.registration.types import (
    FRAME_CHUNK,
    Reference,
    Registration,
    RegistrationError,
    VideoFeatures,
    frame_ranges,
    nonfinite_frames,
    scaled_spec,
)
from motion.render import project_parts
from motion.settings import SettingError, Settings, setting

__all__ = [
    "ApproximateStages",
    "RegistrationSettings",
    "RegistrationSettingsError",
    "approximate_stages",
    "register",
    "silhouette_iou",
]


class RegistrationSettingsError(SettingError, RegistrationError):
    """A pipeline setting outside its type or range (a :class:`RegistrationError` too)."""


@dataclass(frozen=True)
class RegistrationSettings(Settings):
    """Settings of the whole pipeline (each stage's constants live in its own settings; every
    field checked at construction)."""

    setting_error: ClassVar[type[SettingError]] = RegistrationSettingsError

    stage1: Stage1Settings = setting(
        default_factory=Stage1Settings, doc="approximate registration (Stage1Settings)"
    )
    refine: RefineSettings = setting(
        default_factory=RefineSettings, doc="stages 2-3 (RefineSettings)"
    )
    polish: PosturePolishSettings = setting(
        default_factory=PosturePolishSettings,
        doc="the posture polish after them (PosturePolishSettings; steps=0 leaves BP's posture "
        "as it is)",
    )
    scale: float | None = setting(
        None, "the body scale G if known (none: estimated in stage 0)", gt=0
    )
    seed: int = setting(0, "seed of every random draw", ge=0, le=2**32 - 1)
    device: str = setting(
        "cpu",
        "where stages 0-3 and the polish run: cpu, cuda or cuda:N (a GPU and a CUDA build of "
        "torch); the time alignments' dynamic programmes stay on the CPU, and the result "
        "comes back to it. A GPU draws other random numbers than the CPU: the same seed "
        "gives another, equally likely result",
    )

    def validate(self) -> None:
        """Check every field, and that this machine has the device asked for."""
        super().validate()
        try:
            resolve_device(self.device)
        except DeviceError as err:
            raise RegistrationSettingsError(f"{type(self).__name__}: {err}") from None


def silhouette_iou(
    shapes, rig: CameraRig, silhouettes: Tensor, poses: Tensor, chunk: int = FRAME_CHUNK
) -> Tensor:
    """Per frame, the IoU of the rendered body against the observed silhouettes, mean over
    cameras. ``silhouettes`` ``(T', C, H, W)`` in [0, 1] (thresholded at 0.5), ``poses``
    ``(T', P, 7)`` -> ``(T',)``. Rendered ``chunk`` frames at a time."""
    h, w = silhouettes.shape[-2:]
    out = []
    for lo in range(0, poses.shape[0], chunk):
        pose = poses[lo : lo + chunk]
        segments = shapes.segments(pose, torch.arange(shapes.num_parts, device=poses.device))
        parts = project_parts(rig, segments, shapes.radii.to(pose))
        covered = body_layers(parts, h, w).label >= 0
        seen = silhouettes[lo : lo + chunk] > 0.5
        inter = (covered & seen).flatten(2).sum(-1).float()
        union = (covered | seen).flatten(2).sum(-1).float().clamp_min(1)
        out.append((inter / union).mean(-1))
    return torch.cat(out)


def _fill_unseen(stage1: Stage1Result, seen: Tensor) -> Stage1Result:
    """Stage 1's C and T on every frame from its result on the frames ``seen`` ``(T',)``
    (where the person is in view): C interpolated linearly in time between seen frames
    (held beyond the first and last), T from the nearest seen frame. BP then carries the
    unseen frames on their priors and temporal edges."""
    frames = torch.arange(len(seen), dtype=torch.float64, device="cpu")  # NumPy reads it
    known = seen.nonzero().flatten().cpu()
    c = np.interp(frames.numpy(), known.double().numpy(), stage1.C.double().cpu().numpy())
    nearest = (frames[:, None] - known[None].double()).abs().argmin(1)
    return dataclasses.replace(
        stage1,
        C=torch.cummax(torch.from_numpy(c).round().long(), 0).values,
        rotation=stage1.rotation[nearest],
        translation=stage1.translation[nearest],
        cost=stage1.cost[nearest],
    )


def _carry_over_nonfinite(stage1: Stage1Result, name: str) -> tuple[Stage1Result, list[str]]:
    """Stage 1's frames whose ``T`` or cost is NaN or infinite (a pair fit that diverged)
    take C and T from their finite neighbours, as unseen frames do (:func:`_fill_unseen`),
    with a warning naming them; with no finite frame at all, a one-line error."""
    bad = nonfinite_frames(stage1.rotation, stage1.translation, stage1.cost)
    if not len(bad):
        return stage1, []
    frames = stage1.C.shape[0]
    if len(bad) == frames:
        raise RegistrationError(
            f"{name}: stage 1 found no finite body transform on any of the {frames} video "
            "frames (its pair fits diverged to NaN): the silhouettes may not show a body "
            "the reference's postures can cover"
        )
    good = torch.ones(frames, dtype=torch.bool, device="cpu")
    good[bad] = False
    kept = good.nonzero().flatten()
    known = dataclasses.replace(
        stage1,
        C=stage1.C[kept],
        rotation=stage1.rotation[kept],
        translation=stage1.translation[kept],
        cost=stage1.cost[kept],
    )
    warning = (
        f"video frames {frame_ranges(bad)} (counted from the first registered frame): stage 1's "
        "body transform diverged (NaN); they carry their neighbours' C and T"
    )
    return _fill_unseen(known, good), [warning]


@dataclass
class ApproximateStages:
    """Stages 0-1 of :func:`register` (:func:`approximate_stages`).

    Attributes:
        body: stage 0's body scale G (or the one given).
        stage1: stage 1's C and T on every video frame (unseen frames and frames whose fit
            diverged carry their neighbours').
        warnings: the user's sentences on frames whose fit diverged.
        timings: seconds of ``stage0`` and ``stage1``.
        notes: ``G`` (how it was obtained), ``stage1_pairs``, ``unseen_frames`` (if any).
    """

    body: BodyScale
    stage1: Stage1Result
    warnings: list[str]
    timings: dict[str, float]
    notes: dict[str, str]


def approximate_stages(
    reference: Reference,
    video: VideoFeatures,
    settings: RegistrationSettings,
    generator: torch.Generator,
    log: Callable[[str], None] | None = None,
) -> ApproximateStages:
    """Stage 0 (the body scale, unless ``settings.scale`` gives it) and stage 1 (C and T by
    the time alignment of pair fits) on the frames where the person is seen, from one
    ``generator``, as :func:`register` runs them (the inputs on one device, the generator's).
    """
    timings, notes = {}, {}
    t0 = time.perf_counter()
    if settings.scale is None:
        body = estimate_body_scale(reference, video, settings.stage1, generator)
    else:
        body = BodyScale(float(settings.scale), measured=True, note="given")
    notes["G"] = body.note
    timings["stage0"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    seen = video.seen()
    if not bool(seen.any()):
        raise RegistrationError(
            f"{video.name}: the person is never seen (every silhouette is empty)"
        )
    # stage 1 reads no colour: without it, and cut only when some frame is unseen (a cut by
    # indices copies every map)
    shapes_only = dataclasses.replace(
        video, observation=dataclasses.replace(video.observation, image=None)
    )
    if not bool(seen.all()):
        shapes_only = shapes_only.cut(seen.nonzero().flatten())
    stage1 = approximate_registration(
        reference, shapes_only, body.value, settings.stage1, generator, log
    )
    del shapes_only
    if not bool(seen.all()):
        stage1 = _fill_unseen(stage1, seen)
        notes["unseen_frames"] = str(int((~seen).sum()))
    stage1, warnings = _carry_over_nonfinite(stage1, video.name)
    timings["stage1"] = time.perf_counter() - t0
    notes["stage1_pairs"] = str(stage1.pair_evaluations)
    return ApproximateStages(body, stage1, warnings, timings, notes)


def register(
    reference: Reference | str | Path,
    video: VideoFeatures,
    cameras: CameraRig | None = None,
    settings: RegistrationSettings | None = None,
    progress: Progress | None = None,
    log: Callable[[str], None] | None = None,
) -> Registration:
    """Register a reference motion to a video.

    Args:
        reference: a :class:`Reference` or a BVH path.
        video: the video's features and cameras (:class:`VideoFeatures`).
        cameras: a calibrated rig replacing ``video.cameras`` (e.g. the ``rig`` of
            :func:`motion.registration.cameras.initialise_cameras`).
        settings: :class:`RegistrationSettings` (defaults otherwise).
        progress: ``progress(items, description, total)`` wrapping each stage's loop (e.g.
            a tqdm bar); ``None``: silent.
        log: called with a one-line message after each step of stage 1 (``None``:
            silent).

    Returns:
        :class:`Registration`: C, T and A per video frame, G, per-frame silhouette IoU,
        stage 1's C and the seconds per stage.
    """
    s = settings or RegistrationSettings()
    if not isinstance(reference, Reference):
        reference = Reference.from_bvh(reference)
    if cameras is not None:
        video = VideoFeatures(
            video.observation, cameras, video.frame_rate, video.keypoint_joints, video.name
        )
    if video.num_frames < 2:
        raise RegistrationError(
            f"{video.name}: expected at least 2 video frames; got {video.num_frames}"
        )
    device = resolve_device(s.device)
    # every stage runs where its inputs are (each tensor it makes takes their device)
    reference, video = to_device(reference, device), to_device(video, device)
    generator = torch.Generator(device=device).manual_seed(s.seed)
    approximate = approximate_stages(reference, video, s, generator, log)
    body, stage1, warnings = approximate.body, approximate.stage1, approximate.warnings
    scale = body.value
    timings, notes = dict(approximate.timings), dict(approximate.notes)

    t0 = time.perf_counter()
    refined = refine(
        reference,
        video,
        stage1.C,
        stage1.rotation,
        stage1.translation,
        scale,
        s.refine,
        generator,
        progress=progress,
    )
    timings["stages23"] = time.perf_counter() - t0
    warnings += refined.warnings
    notes["stage3_rounds"] = f"{len(refined.c_changes)} (frames changed: {refined.c_changes})"

    c = refined.C
    t0 = time.perf_counter()
    polished = polish_posture(
        reference, video, c, refined.rotations, refined.translation, scale, s.polish, progress
    )
    rotations, translation = polished.rotations.to(refined.rotations), polished.translation
    translation = translation.to(refined.translation)
    timings["polish"] = time.perf_counter() - t0
    if s.polish.steps:
        notes["polish"] = f"loss {polished.loss_start:.1f} -> {polished.loss_end:.1f} nats"
    proportions = polished.proportions
    a = reference.rotations[c].transpose(-1, -2) @ rotations
    a[:, 0] = torch.eye(3, dtype=a.dtype, device=a.device)
    spec = scaled_spec(reference.spec, scale, proportions.part_scales)
    shapes = PartShapes(spec.shapes.axis.float(), spec.shapes.radii.float())
    posture = reference.posture_poses(rotations, scale, proportions.joint_scales())
    poses = place_poses(rotations[:, 0], translation, posture)
    fit = silhouette_iou(
        shapes, video.cameras, video.observation.silhouette[0], poses.to(refined.poses)
    )
    result = Registration(
        C=c,
        T_rotation=rotations[:, 0],
        T_translation=translation,
        A=a,
        G=scale,
        rotations=rotations,
        fit=fit,
        C_stage1=stage1.C,
        timings=timings,
        notes=notes,
        warnings=warnings,
        G_measured=body.measured,
        part_spread_deg=refined.part_spread_deg,
        proportions=proportions if proportions.measured else None,
    )
    return to_device(result, "cpu")  # what reports and exports read
