"""Stage 0's body size ``G`` (:func:`estimate_body_scale` -> :class:`BodyScale`): rigid fits
at ``G = 1``, then a scale factor refined with ``T`` at each sampled video frame's best pair,
the median over frames; only where size is observable (orthographic cameras, or two or more
calibrated perspective cameras), else ``G = 1`` with ``measured=False`` and a note saying why.

``G`` is the student's size relative to the reference (1: the same); metres, radians.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from motion.registration.approximate.cost import _Batch, _levenberg_marquardt
from motion.registration.approximate.pairs import _best, _fit_candidates, _stride
from motion.registration.approximate.scene import _build_scene, _check_inputs, _generator
from motion.registration.approximate.settings import Stage1Settings, _settings
from motion.registration.approximate.starts import _as_pair_init
from motion.registration.types import Reference, RegistrationError, VideoFeatures


@dataclass(frozen=True)
class BodyScale:
    """Stage 0's body size and how it was obtained.

    Attributes:
        value: ``G``, the student's size relative to the reference (1: the same; unitless).
        measured: ``True`` where ``G`` was measured from the video, or given (the pipeline's
            ``RegistrationSettings.scale``); ``False`` where it is 1 because the cameras
            cannot observe size (one perspective camera confounds size and depth).
        note: one line saying how ``G`` was obtained, for reports.
    """

    value: float
    measured: bool
    note: str


def estimate_body_scale(
    reference: Reference,
    video: VideoFeatures,
    settings: Stage1Settings | None = None,
    generator: torch.Generator | None = None,
    frames: int = 8,
) -> BodyScale:
    """Body size G from ``frames`` video frames spread evenly over the video.

    Frames spread over the whole video, rather than its first ones, sample different
    postures: where the student's articulation or a wrong best reference frame biases one
    frame's fit, its neighbours share that bias and a median of consecutive frames keeps it
    (docs/decisions/004-tuning-evidence.md).

    Each frame is fitted (``T`` at G = 1) against ``settings.scale_reference_frames``
    reference frames evenly spaced over the motion, then against every reference frame
    around its best one; at its best pair, ``T`` and a scale factor are refined together
    (``settings.scale_rounds`` times, each at the previous estimate); G is the median over
    frames. Only where the scale is observable: orthographic
    cameras (pixels per metre are known) or two or more calibrated perspective cameras. With
    one perspective camera size and depth are confounded: G = 1, not measured, and a note
    saying so.

    Returns:
        :class:`BodyScale`: G, whether it was measured, and how it was obtained (for reports).

    Raises:
        RegistrationError: bad input, ``frames < 1``.
    """
    st = _settings(settings)
    gen = _generator(generator, video)
    st = dataclasses.replace(
        st, observed_points=st.scale_observed_points, edge_weight=st.scale_edge_weight
    )
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise RegistrationError(f"frames must be an int >= 1; got {frames!r}")
    _check_inputs(reference, video, 1.0)
    rig = video.cameras
    if not rig.orthographic and rig.num_cameras < 2:
        return BodyScale(
            1.0,
            measured=False,
            note="G = 1.0 (not estimated): one perspective camera cannot tell body size from depth",
        )
    nf = min(frames, video.num_frames)
    dev = video.observation.silhouette.device
    video = video.cut(torch.linspace(0, video.num_frames - 1, nf, device=dev).round().long())
    rows = torch.arange(nf, device=dev)
    nref = min(st.scale_reference_frames, reference.num_frames)
    ref = torch.linspace(0, reference.num_frames - 1, nref, device=dev).round().long().unique()
    half = max(1, math.ceil((reference.num_frames - 1) / max(len(ref) - 1, 1) / 2))
    idx = torch.arange(nf, device=dev)
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
        local = (ref[k][:, None] + torch.arange(-half, half + 1, device=dev)).clamp(
            0, reference.num_frames - 1
        )
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
            torch.zeros(nf, dtype=st.dtype, device=dev),
            st.scale_iterations,
            st.lm_damping,
        )
        g_est = float(g_est * log_s.exp().median())
    spread = float(log_s.exp().std()) if nf > 1 else 0.0
    how = "orthographic cameras" if rig.orthographic else f"{rig.num_cameras} calibrated cameras"
    note = (
        f"G = {g_est:.3f} estimated from {how}: median over {nf} video frames spread evenly "
        f"over the video of a rigid fit with free scale at each frame's best reference frame (of {len(ref)} evenly "
        "spaced, then their neighbours) "
        f"(relative spread {spread:.3f})"
    )
    return BodyScale(g_est, measured=True, note=note)
