"""Registration of a 3-D reference motion to video: stages 0-3 of the proposal (Section 6)
as functions with typed inputs and outputs, and :func:`register`, which runs them.

* :mod:`~motion.registration.types` -- :class:`Reference`, :class:`VideoFeatures`,
  :class:`Registration` (C, T, A per video frame, G, fit scores, timings);
* :mod:`~motion.registration.cameras` -- stage 0's cameras (given, from correspondences, or
  one uncalibrated camera's focal length estimated with its pose);
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
