"""Registration of a 3-D reference motion to video: stages 0-3 of the proposal (Section 6)
as functions with typed inputs and outputs, and :func:`register`, which runs them.

* :mod:`~motion.registration.types` -- :class:`Reference`, :class:`VideoFeatures`,
  :class:`Registration` (C, T, A per video frame, G, fit scores, timings);
* :mod:`~motion.registration.cameras` -- stage 0's cameras: a given calibration checked (as
  ``motion register --calibration`` does); for library users who have 2D-3D correspondences,
  extrinsics from them or one camera's focal length estimated with its pose (the command uses
  neither: one video without a calibration gets a nominal 55-degree field of view,
  :data:`motion.registration.video.FIELD_OF_VIEW_DEG`);
* :mod:`~motion.registration.approximate` -- stage 0's body scale and stage 1 (rigid T per
  candidate pair, C by the monotone chain, coarse to fine);
* :mod:`~motion.registration.refine` -- stages 2-3 (particle BP on the spatiotemporal body
  graph, C as a coupled chain in the same graph), windows for long videos;
* :mod:`~motion.registration.pipeline` -- :func:`register`.
"""

from motion.registration.pipeline import RegistrationSettings, register
from motion.registration.types import Reference, Registration, RegistrationError, VideoFeatures

__all__ = [
    "Reference",
    "Registration",
    "RegistrationError",
    "RegistrationSettings",
    "VideoFeatures",
    "register",
]
