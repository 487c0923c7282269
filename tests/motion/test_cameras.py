"""Cameras against OpenCV, DLT recovery, and the shipped pose2sim calibration."""

import dataclasses
import math

import cv2
import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from motion.cameras import (
    CameraFileError,
    CameraRig,
    decompose_projection,
    dlt,
    load_pose2sim_calibration,
    save_pose2sim_calibration,
)
from motion.keypoints import BODY_25B, read_openpose_folder, read_trc
from tests.conftest import SHARED_DATA, requires_shared_data

F64 = torch.float64
TRIAL = SHARED_DATA / "keypoints" / "pose2sim_balancing_trial"
CALIB = SHARED_DATA / "video" / "pose2sim_balancing_trial" / "calibration" / "Calib_qualisys.toml"


def _random_rig(c=3, seed=0, distortion=True):
    g = torch.Generator().manual_seed(seed)
    rvec = torch.randn(c, 3, generator=g, dtype=F64) * 0.3
    k = torch.zeros(c, 3, 3, dtype=F64)
    k[:, 0, 0] = 800 + 100 * torch.rand(c, generator=g, dtype=F64)
    k[:, 1, 1] = k[:, 0, 0] * 1.01
    k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = 320.0, 240.0, 1.0
    dist = torch.randn(c, 5, generator=g, dtype=F64) * torch.tensor(
        [0.1, 0.05, 0.002, 0.002, 0.01], dtype=F64
    )
    if not distortion:
        dist.zero_()
    t = torch.tensor([0.1, -0.2, 4.0], dtype=F64) + 0.1 * torch.randn(c, 3, generator=g, dtype=F64)
    rig = CameraRig(
        k,
        axis_angle_to_rotation_matrix(rvec),
        t,
        dist,
        torch.tensor([[640, 480]] * c, dtype=F64),
        [f"c{i}" for i in range(c)],
    )
    return rig, rvec


def test_projection_matches_opencv_with_distortion():
    rig, rvec = _random_rig()
    pts = torch.randn(2, 50, 3, dtype=F64)
    uv, depth = rig.project(pts)
    assert uv.shape == (2, 3, 50, 2) and depth.shape == (2, 3, 50)
    for c in range(3):
        ref, _ = cv2.projectPoints(
            pts[1].numpy(), rvec[c].numpy(), rig.t[c].numpy(), rig.K[c].numpy(), rig.dist[c].numpy()
        )
        np.testing.assert_allclose(uv[1, c].numpy(), ref[:, 0], atol=1e-8)


def test_dlt_recovers_the_camera_without_noise():
    rig, _ = _random_rig(1, seed=1, distortion=False)
    g = torch.Generator().manual_seed(2)
    pts = torch.randn(40, 3, generator=g, dtype=F64)
    uv, _ = rig.project(pts)
    p = dlt(pts, uv[0])
    k, r, t = decompose_projection(p)
    torch.testing.assert_close(k, rig.K[0], rtol=1e-7, atol=1e-6)
    torch.testing.assert_close(r, rig.R[0], atol=1e-9, rtol=0)
    torch.testing.assert_close(t, rig.t[0], atol=1e-9, rtol=0)
    back, _ = CameraRig.from_projection(p[None], rig.size, ["c"]).project(pts)
    torch.testing.assert_close(back, uv, atol=1e-7, rtol=0)


def test_orthographic_projection():
    k = torch.tensor([[[100.0, 0, 50], [0, 100.0, 60], [0, 0, 1]]], dtype=F64)
    rig = CameraRig(
        k,
        torch.eye(3, dtype=F64)[None],
        torch.zeros(1, 3, dtype=F64),
        torch.zeros(1, 5, dtype=F64),
        torch.tensor([[100, 120]], dtype=F64),
        ["o"],
        orthographic=True,
    )
    uv, _ = rig.project(torch.tensor([[0.1, -0.2, 7.0], [0.1, -0.2, 1.0]], dtype=F64))
    torch.testing.assert_close(uv[0, 0], torch.tensor([60.0, 40.0], dtype=F64))
    torch.testing.assert_close(uv[0, 1], uv[0, 0])


def test_dlt_input_errors():
    with pytest.raises(ValueError, match="at least 6 correspondences"):
        dlt(torch.zeros(5, 3), torch.zeros(5, 2))
    with pytest.raises(ValueError, match=r"points2d \(N, 2\)"):
        dlt(torch.zeros(8, 3), torch.zeros(8, 3))


def test_calibration_file_errors(tmp_path):
    bad = tmp_path / "c.toml"
    bad.write_text('[cam_01]\nname = "cam_01"\nsize = [10.0, 10.0]\n')
    with pytest.raises(CameraFileError, match=r"c\.toml: camera \[cam_01\] has no 'matrix'"):
        load_pose2sim_calibration(bad)
    bad.write_text("not toml [")
    with pytest.raises(CameraFileError, match="not valid TOML"):
        load_pose2sim_calibration(bad)


@requires_shared_data()
@pytest.mark.shared_data
def test_pose2sim_calibration_reprojects_the_triangulated_keypoints():
    """The shipped 3D keypoints, projected with the shipped calibration, land on the shipped
    2D detections: median error 11 px on 1920-px-tall images (the data README's own check),
    asserted below 15 px over all 4 cameras and 100 frames."""
    rig = load_pose2sim_calibration(CALIB)
    assert rig.num_cameras == 4
    markers = read_trc(TRIAL / "pose3d" / "S00_P00_T01_BalancingTrial_0-100.trc")
    trc = torch.from_numpy(markers.positions)
    world = trc[..., [2, 0, 1]]  # X_world = Z_trc, Y_world = X_trc, Z_world = Y_trc
    uv, depth = rig.project(world)
    assert (depth > 0).all()
    shared = [n for n in markers.names if n in BODY_25B]
    m_idx = [markers.names.index(n) for n in shared]
    k_idx = [BODY_25B.index(n) for n in shared]
    errors = []
    for c in range(4):
        det = read_openpose_folder(TRIAL / "pose2d_associated" / f"cam0{c + 1}_json")
        ok = det[:, k_idx, 2] > 0.3
        diff = uv[:, c, m_idx].numpy() - det[:, k_idx, :2]
        errors.append(np.linalg.norm(diff, axis=-1)[ok])
    err = np.concatenate(errors)
    assert len(err) > 4000
    assert np.median(err) < 15.0, np.median(err)
    assert math.isfinite(float(np.percentile(err, 90)))


def _assert_rigs_close(a: CameraRig, b: CameraRig, rtol=1e-9):
    assert a.names == b.names and a.orthographic == b.orthographic
    for key in ("K", "R", "t", "dist", "size"):
        x, y = getattr(a, key).to(F64), getattr(b, key).to(F64)
        assert x.shape == y.shape, key
        # relative to each array's scale (R entries near 0 have no relative precision)
        assert (x - y).abs().max() <= rtol * max(1.0, float(x.abs().max())), key


def test_saved_calibration_reads_back_as_the_same_rig(tmp_path):
    """rig -> Pose2Sim TOML -> rig: equal within 1e-9 relative, including rotations near a half
    turn and the identity (where the Rodrigues vector is delicate) and awkward camera names."""
    rig, _ = _random_rig(c=5, seed=4)
    half_turn = axis_angle_to_rotation_matrix(
        torch.tensor([[0.0, math.pi - 1e-9, 0.0], [0.6 * math.pi, 0.0, -0.8 * math.pi]], dtype=F64)
    )
    rig.R[0], rig.R[1], rig.R[2] = half_turn[0], half_turn[1], torch.eye(3, dtype=F64)
    rig.names = ["cam 01", 'q"uote', "back\\slash", "tab\there", "é"]
    path = save_pose2sim_calibration(rig, tmp_path / "calib.toml")
    assert path == tmp_path / "calib.toml"
    _assert_rigs_close(load_pose2sim_calibration(path), rig)
    text = path.read_text()
    assert text.count("fisheye = false") == 5 and "[metadata]" in text


@requires_shared_data()
@pytest.mark.shared_data
def test_the_shipped_calibration_survives_a_save_and_load(tmp_path):
    rig = load_pose2sim_calibration(CALIB)
    back = load_pose2sim_calibration(save_pose2sim_calibration(rig, tmp_path / "c.toml"))
    _assert_rigs_close(back, rig)


def test_saving_a_calibration_refuses_what_the_format_cannot_hold(tmp_path):
    rig, _ = _random_rig(c=2)
    with pytest.raises(ValueError, match="distinct and not 'metadata'"):
        save_pose2sim_calibration(dataclasses.replace(rig, names=["a", "a"]), tmp_path / "x.toml")
    with pytest.raises(ValueError, match="orthographic"):
        save_pose2sim_calibration(dataclasses.replace(rig, orthographic=True), tmp_path / "x.toml")
    bad = dataclasses.replace(rig, t=rig.t.clone())
    bad.t[1, 2] = float("nan")
    with pytest.raises(ValueError, match=r"rig\.t must be finite"):
        save_pose2sim_calibration(bad, tmp_path / "x.toml")
    assert not (tmp_path / "x.toml").exists()
