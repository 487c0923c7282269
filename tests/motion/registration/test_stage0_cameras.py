"""Stage 0, the cameras: given, from correspondences, focal estimated -- against OpenCV.

Cameras are built like :mod:`motion.synth`'s (on a circle, looking at the body) or at random;
the points are random or the walk's skeleton joints (``motion/data/cmu_02_01_walk.bvh``).
The independent answers are OpenCV's: ``solvePnP`` (``SOLVEPNP_ITERATIVE``, Levenberg-Marquardt
on the reprojection error) for the extrinsics, ``calibrateCamera`` with the principal point,
aspect ratio and zero distortion fixed for the focal length. Both minimise the same objective
as ours, so once converged the answers agree far more closely than either agrees with the
truth under pixel noise (measured: ~1e-5 degrees and ~1e-7 relative focal, against ~0.5
degrees and ~0.3 % from the truth at 0.5 px noise).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from motion.bvh import read_bvh
from motion.cameras import CameraRig, load_pose2sim_calibration
from motion.kinematics import Skeleton, forward_kinematics, local_rotations
from motion.registration.cameras import (
    SOURCES,
    cameras_from_correspondences,
    estimate_focal_and_pose,
    initialise_cameras,
    reprojection_rms,
)
from motion.registration.types import RegistrationError
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.test_bvh import BUNDLED

F64 = torch.float64
W, H = 640, 480
CALIB_FLAGS = (
    cv2.CALIB_USE_INTRINSIC_GUESS
    | cv2.CALIB_FIX_PRINCIPAL_POINT
    | cv2.CALIB_FIX_ASPECT_RATIO
    | cv2.CALIB_ZERO_TANGENT_DIST
    | cv2.CALIB_FIX_K1
    | cv2.CALIB_FIX_K2
    | cv2.CALIB_FIX_K3
)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Small batched problems on 2 shared cores: torch's intra-op threads slow them several
    times over (as tests/conftest.py notes for xdist workers)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def walk() -> torch.Tensor:
    """``(F, 31, 3)`` the walk's joint positions, metres, world Y up."""
    bvh = read_bvh(BUNDLED)
    skeleton = Skeleton.from_bvh(bvh)
    rot, root = local_rotations(skeleton, torch.from_numpy(bvh.motion_frames()), bvh.channels)
    return forward_kinematics(skeleton, rot, root).positions


def _look_at(eyes: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> tuple:
    """World-to-camera ``R (C, 3, 3)``, ``t (C, 3)`` of cameras at ``eyes (C, 3)`` looking at
    ``target (3,)``, ``up (C, 3)`` roughly up in the image (rows: right, down, forward)."""
    fwd = torch.nn.functional.normalize(target - eyes, dim=-1)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, up), dim=-1)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd], -2)
    return R, -(R @ eyes.unsqueeze(-1)).squeeze(-1)


def _rig(K: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> CameraRig:
    c = K.shape[0]
    size = torch.tensor([[W, H]] * c, dtype=F64)
    return CameraRig(K, R, t, torch.zeros(c, 5, dtype=F64), size, [f"cam{i + 1}" for i in range(c)])


def _intrinsics(fx, fy=None, cx=W / 2, cy=H / 2) -> torch.Tensor:
    fy = fx if fy is None else fy
    return torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=F64)


def _circle_rig(centre: torch.Tensor, c=4, focal=500.0, distance=4.0, height=1.0) -> CameraRig:
    """As motion.synth's: ``c`` cameras on a horizontal circle around ``centre`` at
    ``height`` metres (world Y up), looking at it."""
    a = 2 * math.pi * torch.arange(c, dtype=F64) / c
    eyes = centre + distance * torch.stack([a.sin(), torch.zeros_like(a), a.cos()], -1)
    eyes[:, 1] = height
    R, t = _look_at(eyes, centre, torch.tensor([0.0, 1.0, 0.0], dtype=F64).expand(c, 3))
    return _rig(_intrinsics(focal).expand(c, 3, 3).clone(), R, t)


def _random_rig(c=3, seed=0) -> CameraRig:
    """Cameras 3-6 m from the origin in random directions and rolls, random intrinsics
    (fx 400-1200 px, fy within 2 %, principal point within 20 px of the centre)."""
    g = torch.Generator().manual_seed(seed)
    direction = torch.nn.functional.normalize(torch.randn(c, 3, generator=g, dtype=F64), dim=-1)
    eyes = direction * (3 + 3 * torch.rand(c, 1, generator=g, dtype=F64))
    up = torch.randn(c, 3, generator=g, dtype=F64)
    R, t = _look_at(eyes, torch.zeros(3, dtype=F64), up)
    u = torch.rand(c, 4, generator=g, dtype=F64)
    K = torch.stack(
        [
            _intrinsics(
                400 + 800 * float(u[i, 0]),
                (400 + 800 * float(u[i, 0])) * (0.98 + 0.04 * float(u[i, 1])),
                W / 2 + 40 * float(u[i, 2]) - 20,
                H / 2 + 40 * float(u[i, 3]) - 20,
            )
            for i in range(c)
        ]
    )
    return _rig(K, R, t)


def _noise(shape, sigma=0.5, seed=1) -> torch.Tensor:
    return sigma * torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


def _angle_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Rotation angle between rotation matrices (any leading shape), degrees."""
    rel = (a.transpose(-1, -2) @ b).reshape(-1, 3, 3)
    return torch.rad2deg(rotation_matrix_to_axis_angle(rel).norm(dim=-1)).reshape(a.shape[:-2])


def _opencv_pnp(X: torch.Tensor, x: torch.Tensor, K: torch.Tensor):
    """cv2.solvePnP (SOLVEPNP_ITERATIVE) -> R (3, 3), t (3,), sum of squared residuals."""
    X, x = X.numpy(), x.numpy()
    ok, rvec, tvec = cv2.solvePnP(X, x, K.numpy(), None, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    proj, _ = cv2.projectPoints(X, rvec, tvec, K.numpy(), None)
    sse = float(((proj[:, 0] - x) ** 2).sum())
    R = axis_angle_to_rotation_matrix(torch.from_numpy(rvec.T))[0]
    return R, torch.from_numpy(tvec[:, 0]), sse


def _sse(rig: CameraRig, c: int, X: torch.Tensor, x: torch.Tensor) -> float:
    uv, _ = rig.project(X)
    return float((uv[c] - x).square().sum())


# ---------------------------------------------------------------------------------------------
# route 1: a given calibration
# ---------------------------------------------------------------------------------------------


def test_given_rig_passes_through_and_reports_its_rms(walk):
    X = walk[:3].reshape(-1, 3)  # 3 frames of 31 joints seen by static cameras: (93, 3)
    rig = _circle_rig(X.mean(0))
    uv, _ = rig.project(X)
    init = initialise_cameras(rig)
    assert init.rig is rig and init.source == "given" and init.rms_px is None
    assert "no correspondences" in init.note and "\n" not in init.note
    exact = initialise_cameras(rig, X, uv)
    assert exact.rig is rig and exact.rms_px.shape == (4,) and exact.rms_px.max() < 1e-9
    # 0.5 px per coordinate: the RMS of the 2-D residual is sqrt(2) * 0.5 = 0.71 px
    noisy = initialise_cameras(rig, X, uv + _noise(uv.shape))
    assert ((noisy.rms_px > 0.6) & (noisy.rms_px < 0.8)).all(), noisy.rms_px
    # missing rows are skipped; a camera with none present has no RMS
    gappy = uv.clone()
    gappy[0, :10] = math.nan
    gappy[2] = math.nan
    rms = reprojection_rms(rig, X, gappy)
    assert rms[[0, 1, 3]].max() < 1e-9 and rms[2].isnan()


def _set(field: str, index, value):
    """A change to a copy of the rig: ``rig.field[index] = value``."""

    def change(rig: CameraRig) -> None:
        getattr(rig, field)[index] = value

    return change


def _replace(field: str, value):
    """A change to a copy of the rig: ``rig.field = value``."""
    return lambda rig: setattr(rig, field, value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (_set("K", (1, 0, 0), -500.0), r"cam2: K must be \[\[fx, s, cx\].* fx, fy > 0"),
        (_set("K", (0, 2, 0), 0.1), r"cam1: K must be .*\[0, 0, 1\]"),
        (_set("K", (0, 0, 2), math.inf), r"K must be finite; got 1 NaN or infinite"),
        (_set("t", (3, 1), math.nan), r"rig\.t must be finite"),
        (_set("R", (2, 0), torch.tensor([1.0, 1.0, 0.0])), r"cam3: rig\.R must be a rotation"),
        (_set("R", (1, 0), -_circle_rig(torch.zeros(3, dtype=F64)).R[1, 0]), r"cam2: .*det -1"),
        (_set("size", (0, 1), 0.0), r"at least 1 x 1 pixel"),
        (_replace("names", ["a", "b"]), r"names must be 4 strings"),
        (_replace("names", ["a", "b", "a", "c"]), r"names must be unique; repeated: \['a'\]"),
        (_replace("dist", torch.zeros(4, 4)), r"rig\.dist must be \(4, 5\); got \(4, 4\)"),
        (_replace("t", torch.zeros(3, 3)), r"rig\.t must be \(4, 3\); got \(3, 3\)"),
    ],
)
def test_given_rig_errors(change, message):
    rig = _circle_rig(torch.zeros(3, dtype=F64))
    bad = CameraRig(
        rig.K.clone(), rig.R.clone(), rig.t.clone(), rig.dist.clone(), rig.size.clone(), rig.names
    )
    change(bad)
    with pytest.raises(RegistrationError, match=message):
        initialise_cameras(bad)


def test_given_rig_input_errors(walk):
    rig = _circle_rig(walk[0].mean(0))
    uv, _ = rig.project(walk[0])
    with pytest.raises(RegistrationError, match=r"must be a motion\.cameras\.CameraRig; got dict"):
        initialise_cameras({"K": rig.K})
    with pytest.raises(RegistrationError, match="expected none of K, size, names beside it, got K"):
        initialise_cameras(rig, walk[0], uv, K=rig.K)
    with pytest.raises(RegistrationError, match=r"points2d must be \(4, N, 2\)"):
        initialise_cameras(rig, walk[0], uv[:2])
    # the body behind camera 3: the given calibration cannot have seen it
    behind = walk[0] + 2 * (rig.centres()[2] - walk[0].mean(0))
    uv_b, _ = rig.project(behind)
    with pytest.raises(RegistrationError, match=r"cam3: 31 of 31 points are behind the camera"):
        initialise_cameras(rig, behind, uv_b)


# ---------------------------------------------------------------------------------------------
# route 2: extrinsics from correspondences, known intrinsics
# ---------------------------------------------------------------------------------------------


def _scene(name: str, walk: torch.Tensor) -> tuple[CameraRig, torch.Tensor]:
    if name == "walk":  # cameras around the walker; 3 frames of its joints, static cameras
        X = walk[::100][:3].reshape(-1, 3)
        return _circle_rig(X.mean(0)), X
    g = torch.Generator().manual_seed(4)
    return _random_rig(4, seed=3), torch.rand(40, 3, generator=g, dtype=F64) - 0.5


@pytest.mark.parametrize("scene", ["walk", "random"])
def test_extrinsics_agree_with_opencv_solvepnp(scene, walk):
    """0.5 px noise moves both solutions ~0.1-1 degree from the truth; as converged
    minimisers of the same reprojection error they agree to ~1e-5 degree (measured), so
    1e-3 degree and 0.1 mm (100x that, 1/100 of the noise's effect) are asserted, and our
    cost is never above OpenCV's."""
    rig, X = _scene(scene, walk)
    uv, depth = rig.project(X)
    assert (depth > 0).all()
    obs = uv + _noise(uv.shape)
    init = initialise_cameras(points3d=X, points2d=obs, K=rig.K, size=rig.size)
    assert init.source == "correspondences" and init.rig.names == rig.names
    assert ((init.rms_px > 0.55) & (init.rms_px < 0.85)).all(), init.rms_px
    assert "\n" not in init.note and "RMS" in init.note
    torch.testing.assert_close(init.rig.K, rig.K)
    assert _angle_deg(rig.R, init.rig.R).max() < 2.0
    assert (init.rig.centres() - rig.centres()).norm(dim=-1).max() < 0.2
    for c in range(rig.num_cameras):
        R_cv, t_cv, sse_cv = _opencv_pnp(X, obs[c], rig.K[c])
        assert _angle_deg(R_cv, init.rig.R[c]) < 1e-3
        assert (t_cv - init.rig.t[c]).norm() < 1e-4
        assert _sse(init.rig, c, X, obs[c]) <= sse_cv * (1 + 1e-9)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_noise_free_extrinsics_are_exact(dtype):
    rig = _random_rig(3, seed=5)
    X = torch.rand(12, 3, generator=torch.Generator().manual_seed(6), dtype=F64) - 0.5
    uv, _ = rig.project(X)
    out = cameras_from_correspondences(X.to(dtype), uv.to(dtype), rig.K.to(dtype), rig.size)
    assert out.R.dtype == dtype and out.t.dtype == dtype and out.names == ["cam1", "cam2", "cam3"]
    atol = 1e-9 if dtype == torch.float64 else 2e-4  # float32 pixels: 3e-5 px at 500 px
    torch.testing.assert_close(out.R.double(), rig.R, atol=atol, rtol=0)
    torch.testing.assert_close(out.t.double(), rig.t, atol=10 * atol, rtol=0)
    assert (out.dist == 0).all() and torch.equal(out.size, rig.size.to(dtype))


def test_missing_correspondences_are_masked():
    """NaN rows are dropped per camera (different counts per camera, one left with exactly
    6; a NaN 3-D row is missing for all); each camera equals OpenCV on its present rows."""
    rig = _random_rig(3, seed=7)
    X = torch.rand(20, 3, generator=torch.Generator().manual_seed(8), dtype=F64) - 0.5
    uv, _ = rig.project(X)
    obs = uv + _noise(uv.shape, seed=9)
    X_gappy = X.clone()
    X_gappy[4] = math.nan
    obs[1, [0, 7, 11]] = math.nan
    obs[2, 6:19] = math.nan  # with row 4: 6 present
    init = initialise_cameras(
        points3d=X_gappy, points2d=obs, K=rig.K, size=rig.size, names=["a", "b", "c"]
    )
    present = ~(X_gappy.isnan().any(-1) | obs.isnan().any(-1))
    assert present.sum(-1).tolist() == [19, 16, 6]
    assert torch.isfinite(init.rms_px).all()
    for c in range(3):
        ok = present[c]
        R_cv, t_cv, _ = _opencv_pnp(X[ok], obs[c, ok], rig.K[c])
        assert _angle_deg(R_cv, init.rig.R[c]) < 1e-3
        assert (t_cv - init.rig.t[c]).norm() < 1e-3
        alone = cameras_from_correspondences(
            X[ok], obs[c, ok][None], rig.K[c : c + 1], rig.size[:1]
        )
        torch.testing.assert_close(alone.R[0], init.rig.R[c], atol=1e-9, rtol=0)


def _route2_inputs():
    rig = _random_rig(3, seed=10)
    X = torch.rand(20, 3, generator=torch.Generator().manual_seed(11), dtype=F64) - 0.5
    uv, _ = rig.project(X)
    return {"points3d": X, "points2d": uv, "K": rig.K, "size": rig.size}


def _few(d):
    d["points2d"][1, 5:] = math.nan


def _nan_camera(d):
    d["points2d"][0] = math.nan


def _inf(d):
    d["points3d"][3, 1] = math.inf


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (_few, r"cam2: needs at least 6 2D-3D correspondences without NaN; got 5 of 20"),
        (_nan_camera, r"cam1: needs at least 6 2D-3D correspondences without NaN; got 0 of 20"),
        (_inf, r"points3d must be finite or NaN \(missing\); got 1 infinite"),
        (lambda d: d.update(points2d=d["points2d"][0]), r"points2d must be \(C, N, 2\) pixels"),
        (
            lambda d: d.update(points3d=d["points3d"][:19]),
            r"points3d must be \(20, 3\) or \(3, 20, 3\)",
        ),
        (
            lambda d: d.update(K=d["K"][0]),
            r"K must be \(3, 3, 3\) intrinsics, pixels; got \(3, 3\)",
        ),
        (lambda d: d.update(size=d["size"][0]), r"size must be \(3, 2\) image \[width, height\]"),
        (lambda d: d.update(names=["a", "b"]), r"names must be 3 strings"),
        (lambda d: d["K"].__setitem__((2, 1, 1), 0.0), r"cam3: K must be .* fx, fy > 0"),
        (lambda d: d.update(points2d="nope"), r"points2d must be an array of numbers; got str"),
    ],
)
def test_correspondence_errors(change, message):
    inputs = _route2_inputs()
    inputs = {k: v.clone() for k, v in inputs.items()}
    change(inputs)
    with pytest.raises(RegistrationError, match=message):
        initialise_cameras(**inputs)


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("straddling", r"cam1: \d+ of 20 points are behind the camera"),
        ("all behind", r"cam1: the correspondences fit only a mirror-image camera"),
        ("x flipped", r"cam1: the correspondences fit only a mirror-image camera"),
    ],
)
def test_points_behind_the_camera_or_mirrored_pixels_are_refused(case, message):
    """Pixels no real camera can produce: points on both sides of the camera, all behind it
    (a point reflection through the centre: a mirror image), or the u axis flipped. The
    last two fit a DLT camera with det < 0 exactly, and no rotation."""
    g = torch.Generator().manual_seed(12)
    X = torch.randn(20, 3, generator=g, dtype=F64)
    depth = {"straddling": 1.0, "all behind": -6.0, "x flipped": 6.0}[case]
    if case == "straddling":
        X[:, 2] *= 3
    pc = X + torch.tensor([0.0, 0.0, depth], dtype=F64)
    K = _intrinsics(500.0)
    uv = pc[:, :2] / pc[:, 2:] * 500 + K[:2, 2]
    if case == "x flipped":
        uv[:, 0] = W - uv[:, 0]
    assert ((pc[:, 2] < 0).sum() > 0) == (case != "x flipped")
    with pytest.raises(RegistrationError, match=message):
        cameras_from_correspondences(X, uv[None], K[None], torch.tensor([[W, H]]))
    if case == "x flipped":
        with pytest.raises(RegistrationError, match=r"view 0: .*mirror-image camera"):
            estimate_focal_and_pose(X, uv, torch.tensor([W, H]))


# ---------------------------------------------------------------------------------------------
# route 3: one uncalibrated camera, focal estimated
# ---------------------------------------------------------------------------------------------


def _body_views(walk: torch.Tensor, focal: float, views=4, seed=13, sigma=0.5):
    """The walker's joints (centred) in ``views`` random orientations 2.5 m in front of one
    camera (a calibration object moved around): points (F, 31, 3), clean and noisy pixels
    (F, 31, 2), true R (F, 3, 3)."""
    g = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, walk.shape[0], (views,), generator=g)
    X = walk[frames] - walk[frames].mean(1, keepdim=True)
    R = axis_angle_to_rotation_matrix(0.5 * torch.randn(views, 3, generator=g, dtype=F64))
    t = torch.tensor([0.0, 0.0, 2.5], dtype=F64) + 0.3 * torch.randn(
        views, 3, generator=g, dtype=F64
    )
    pc = X @ R.transpose(-1, -2) + t[:, None]
    uv = pc[..., :2] / pc[..., 2:] * focal + torch.tensor([W / 2, H / 2], dtype=F64)
    return X, uv, uv + _noise(uv.shape, sigma, seed + 1), R


def test_focal_agrees_with_opencv_calibrate_camera_and_the_truth(walk):
    """4 views of the walker's 31 joints, 0.5 px noise: the focal within 2 % of the truth
    (measured 0.1-0.3 % over seeds) and within 1e-5 of OpenCV's (measured ~1e-7: the same
    objective), with the same RMS and per-view rotations."""
    focal = 600.0
    X, _, obs, R_true = _body_views(walk, focal)
    est = estimate_focal_and_pose(X, obs, torch.tensor([W, H]))
    guess = _intrinsics(float(W))  # an initial guess OpenCV needs for non-planar points
    rms_cv, K_cv, _, rvecs, _ = cv2.calibrateCamera(
        [x.numpy().astype(np.float32) for x in X],
        [x.numpy().astype(np.float32) for x in obs],
        (W, H),
        guess.numpy(),
        np.zeros(5),
        flags=CALIB_FLAGS,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12),
    )
    f_cv = K_cv[0, 0]
    assert abs(est.focal_px / focal - 1) < 0.02, est.focal_px
    assert abs(est.focal_px / f_cv - 1) < 1e-5, (est.focal_px, f_cv)
    assert abs(est.rms_px / rms_cv - 1) < 1e-5, (est.rms_px, rms_cv)
    R_cv = axis_angle_to_rotation_matrix(torch.from_numpy(np.concatenate(rvecs, 1).T))
    assert _angle_deg(R_cv, est.R).max() < 1e-3
    assert _angle_deg(R_true, est.R).max() < 2.0
    assert est.R.shape == (4, 3, 3) and est.t.shape == (4, 3) and est.view_rms_px.shape == (4,)
    torch.testing.assert_close(est.K, _intrinsics(est.focal_px))
    # the reported cost curve has its minimum at the grid point nearest the estimate
    nearest = (est.grid_focal_px.log() - math.log(est.focal_px)).abs().argmin()
    assert int(est.grid_rms_px.argmin()) == int(nearest)


@pytest.mark.parametrize("multiple", [0.35, 1.0, 4.0])
def test_noise_free_focal_is_exact_across_the_range(multiple):
    """Fields of view from 110 to 14 degrees across: the truth to ~1e-9 relative (the
    search tolerance) with random points in 2 views at a distance that fills the image."""
    focal = multiple * W
    g = torch.Generator().manual_seed(14)
    X = torch.rand(2, 15, 3, generator=g, dtype=F64) - 0.5
    R = axis_angle_to_rotation_matrix(torch.randn(2, 3, generator=g, dtype=F64))
    t = torch.tensor([0.0, 0.0, 0.5 + focal / W], dtype=F64).expand(2, 3)
    pc = X @ R.transpose(-1, -2) + t[:, None]
    uv = pc[..., :2] / pc[..., 2:] * focal + torch.tensor([W / 2, H / 2], dtype=F64)
    est = estimate_focal_and_pose(X, uv, torch.tensor([W, H]))
    assert abs(est.focal_px / focal - 1) < 1e-8, est.focal_px
    torch.testing.assert_close(est.R, R, atol=1e-7, rtol=0)
    torch.testing.assert_close(est.t, t, atol=1e-6, rtol=0)
    assert est.rms_px < 1e-5


def test_single_view_shapes_dtype_and_principal_point(walk):
    X, uv, _, R_true = _body_views(walk, 500.0, views=1, seed=15)
    pp = torch.tensor([300.0, 250.0])
    uv = uv[0] + (pp.double() - torch.tensor([W / 2, H / 2], dtype=F64))  # pixels about pp
    est = estimate_focal_and_pose(X[0].float(), uv.float(), torch.tensor([W, H]), pp)
    assert est.R.shape == (3, 3) and est.t.shape == (3,) and est.view_rms_px.shape == ()
    assert est.R.dtype == torch.float32 and est.K.dtype == torch.float32
    assert est.grid_focal_px.shape == est.grid_rms_px.shape == (41,)
    torch.testing.assert_close(est.K[:2, 2], pp)
    assert abs(est.focal_px / 500 - 1) < 1e-3  # float32 pixels (~3e-5 px), one view
    assert _angle_deg(R_true[0], est.R.double()) < 0.05
    assert "focal" in est.note and "\n" not in est.note


def test_focal_errors(walk):
    X, uv, _, _ = _body_views(walk, 600.0, views=2, seed=16)
    size = torch.tensor([W, H])
    with pytest.raises(
        RegistrationError, match=r"^focal length at the upper end of the search range 0\.3-0\.6 x"
    ):
        estimate_focal_and_pose(X, uv, size, focal_range=(0.3, 0.6))
    few = uv.clone()
    few[1, 5:] = math.nan
    with pytest.raises(RegistrationError, match=r"view 1: needs at least 6 .* got 5 of 31"):
        estimate_focal_and_pose(X, few, size)
    with pytest.raises(RegistrationError, match=r"size must be \(2,\) image \[width, height\]"):
        estimate_focal_and_pose(X, uv, torch.tensor([[W, H]]))
    with pytest.raises(RegistrationError, match=r"0 < lo < hi; got \(5\.0, 0\.3\)"):
        estimate_focal_and_pose(X, uv, size, focal_range=(5.0, 0.3))
    with pytest.raises(RegistrationError, match=r"grid must be an integer >= 5; got 3"):
        estimate_focal_and_pose(X, uv, size, grid=3)
    with pytest.raises(RegistrationError, match=r"points2d must be \(N, 2\) or \(F, N, 2\)"):
        estimate_focal_and_pose(X, X, size)
    with pytest.raises(RegistrationError, match=r"principal_point must be \(2,\) pixels"):
        estimate_focal_and_pose(X, uv, size, principal_point=torch.zeros(3))


# ---------------------------------------------------------------------------------------------
# the dispatcher
# ---------------------------------------------------------------------------------------------


def test_dispatcher_estimates_each_cameras_focal_without_k(walk):
    """No K: each camera's focal and pose from its own view of the world points; without
    noise the rig is recovered (the image centre is synth's principal point)."""
    X = walk[::100][:3].reshape(-1, 3)
    rig = _circle_rig(X.mean(0), c=2, focal=450.0, distance=3.0)
    uv, _ = rig.project(X)
    init = initialise_cameras(points3d=X, points2d=uv, size=rig.size)
    assert init.source == "focal estimated" and init.source in SOURCES
    torch.testing.assert_close(init.rig.K, rig.K, atol=1e-5, rtol=0)
    torch.testing.assert_close(init.rig.R, rig.R, atol=1e-8, rtol=0)
    assert init.rms_px.shape == (2,) and init.rms_px.max() < 1e-5
    assert "cam1 f=450.0 px" in init.note and "\n" not in init.note


def test_dispatcher_errors(walk):
    rig = _circle_rig(walk[0].mean(0))
    uv, _ = rig.project(walk[0])
    with pytest.raises(RegistrationError, match=r"needs a calibrated rig.*; got nothing"):
        initialise_cameras()
    with pytest.raises(RegistrationError, match="need both points3d and points2d; got no points2d"):
        initialise_cameras(points3d=walk[0])
    with pytest.raises(RegistrationError, match=r"image size .*; got K, points3d, points2d"):
        initialise_cameras(points3d=walk[0], points2d=uv, K=rig.K)
    with pytest.raises(RegistrationError, match=r"got K, size$"):
        initialise_cameras(K=rig.K, size=rig.size)


# ---------------------------------------------------------------------------------------------
# real data: the shipped 4-camera calibration and keypoints
# ---------------------------------------------------------------------------------------------

TRIAL = SHARED_DATA / "keypoints" / "pose2sim_balancing_trial"
CALIB = SHARED_DATA / "video" / "pose2sim_balancing_trial" / "calibration" / "Calib_qualisys.toml"


@requires_shared_data()
@pytest.mark.shared_data
def test_real_calibration_and_extrinsics_from_real_keypoints():
    """The shipped calibration passes as given; from the shipped triangulated 3-D keypoints
    and OpenPose detections (undistorted with the file's distortion, low confidence masked)
    of 20 frames, the extrinsics come back within 2.5 degrees and 10 cm of the file's (the
    detections are 10-45 px RMS off the markers), agree with OpenCV, and fit at least as
    well as the file's cameras do on the same pixels."""
    from motion.keypoints import BODY_25B, read_openpose_folder, read_trc

    rig = load_pose2sim_calibration(CALIB)
    assert initialise_cameras(rig).source == "given"
    markers = read_trc(TRIAL / "pose3d" / "S00_P00_T01_BalancingTrial_0-100.trc")
    world = torch.from_numpy(markers.positions)[..., [2, 0, 1]]  # trc axes to the rig's world
    shared = [n for n in markers.names if n in BODY_25B]
    X = world[::5][:, [markers.names.index(n) for n in shared]].reshape(-1, 3)
    pixels = []
    for c in range(4):
        det = read_openpose_folder(TRIAL / "pose2d_associated" / f"cam0{c + 1}_json")
        det = det[::5][:, [BODY_25B.index(n) for n in shared]].reshape(-1, 3)
        K, dist = rig.K[c].numpy(), rig.dist[c].numpy()
        und = cv2.undistortPoints(det[:, None, :2].astype(np.float64), K, dist, P=K)[:, 0]
        und[det[:, 2] <= 0.3] = np.nan
        pixels.append(und)
    x2 = torch.from_numpy(np.stack(pixels))
    init = initialise_cameras(points3d=X, points2d=x2, K=rig.K, size=rig.size, names=rig.names)
    assert _angle_deg(rig.R, init.rig.R).max() < 2.5
    assert (init.rig.centres() - rig.centres()).norm(dim=-1).max() < 0.1
    undistorted = CameraRig(rig.K, rig.R, rig.t, torch.zeros_like(rig.dist), rig.size, rig.names)
    given = initialise_cameras(undistorted, X, x2)
    assert (init.rms_px <= given.rms_px * (1 + 1e-9)).all(), (init.rms_px, given.rms_px)
    for c in range(4):
        ok = ~x2[c].isnan().any(-1)
        R_cv, _, sse_cv = _opencv_pnp(X[ok], x2[c, ok], rig.K[c])
        assert _angle_deg(R_cv, init.rig.R[c]) < 2e-3  # ~0.5 % of the distance to the file's
        assert _sse(init.rig, c, X[ok], x2[c, ok]) <= sse_cv * (1 + 1e-9)
