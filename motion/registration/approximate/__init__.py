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

Modules: :mod:`~motion.registration.approximate.settings` (:class:`Stage1Settings`),
:mod:`~motion.registration.approximate.scene` (what is fixed during a call: the video's maps,
the reference's geometry), :mod:`~motion.registration.approximate.cost` (a pair's image cost
and its Levenberg-Marquardt fit), :mod:`~motion.registration.approximate.starts` (initial
transforms), :mod:`~motion.registration.approximate.pairs` (the best ``T`` of each pair, the
heading prior), :mod:`~motion.registration.approximate.scale` (stage 0's body scale ``G``),
:mod:`~motion.registration.approximate.registration` (``C``, then ``T`` per video frame).
"""

from motion.registration.approximate.cost import pair_costs
from motion.registration.approximate.pairs import PairFit, fit_rigid_pairs
from motion.registration.approximate.registration import Stage1Result, approximate_registration
from motion.registration.approximate.scale import BodyScale, estimate_body_scale
from motion.registration.approximate.settings import Stage1Settings

__all__ = [
    "BodyScale",
    "PairFit",
    "Stage1Result",
    "Stage1Settings",
    "approximate_registration",
    "estimate_body_scale",
    "fit_rigid_pairs",
    "pair_costs",
]
