import math

import torch
from scipy.spatial.transform import Rotation

from motion.metrics import (
    articulation_error_deg,
    correspondence_error,
    joint_error_2d,
    joint_error_3d,
    position_error,
    registration_error,
    rotation_angle_error_deg,
    rotation_error_deg,
    silhouette_iou,
)

F64 = torch.float64


def test_registration_error_eq21():
    obs = torch.zeros(4, 2, dtype=F64)
    proj = obs.clone()
    proj[0] = torch.tensor([3.0, 4.0])  # squared residual 25
    assert registration_error(proj, obs, 280.0).item() == 25 / (4 * 280)


def test_rotation_errors_eq22_and_geodesic():
    a = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    b = a + torch.tensor([0.03, 0.0, -0.04], dtype=F64)
    assert math.isclose(rotation_error_deg(a, b).item(), math.degrees(0.05) / 3, rel_tol=1e-12)
    # wrap-around: 179 deg vs -179 deg differ by 2 deg
    w = rotation_error_deg(
        torch.tensor([math.radians(179), 0, 0]), torch.tensor([math.radians(-179), 0, 0])
    )
    assert math.isclose(w.item(), 2 / 3, rel_tol=1e-5)
    r1 = torch.from_numpy(Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix())
    r2 = r1 @ torch.from_numpy(Rotation.from_rotvec([0.0, 0.0, math.radians(7)]).as_matrix())
    assert math.isclose(rotation_angle_error_deg(r1, r2).item(), 7.0, rel_tol=1e-9)
    assert articulation_error_deg(torch.stack([r1, r1]), torch.stack([r2, r1])).tolist()[1] < 1e-5


def test_position_and_joint_errors_eq23_36_37():
    p = torch.zeros(3, dtype=F64)
    assert position_error(p, torch.tensor([0.0, 0.3, 0.4], dtype=F64), 1.95).item() == 0.5 / 1.95
    true = torch.zeros(2, 3, dtype=F64)
    est = torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.4, 0.0]], dtype=F64)
    assert math.isclose(joint_error_3d(true, est, 2.0).item(), (1.0 + 0.5) / 2 / 2.0)
    assert math.isclose(joint_error_2d(true, est, 2.0).item(), (0.0 + 0.5) / 2 / 2.0)


def test_correspondence_error_and_iou():
    frames, ms = correspondence_error(torch.tensor([0, 4, 8]), torch.tensor([1, 4, 6]), 120.0)
    assert frames.item() == 1.0 and math.isclose(ms.item(), 1000 / 120)
    a = torch.zeros(4, 4, dtype=torch.bool)
    b = torch.zeros(4, 4, dtype=torch.bool)
    a[:2] = True
    b[1:3] = True
    assert silhouette_iou(a, b).item() == 4 / 12
    assert silhouette_iou(torch.zeros(2, 2), torch.zeros(2, 2)).item() == 1.0
