import math

import pytest
import torch

from motion.bvh import read_bvh
from motion.kinematics import Skeleton, local_rotations, matrix_to_euler
from motion.limits import limit_violation, limits_tensor, load_limits
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.test_bvh import BUNDLED


def _angles(bvh, skel, frames):
    """Each joint's Euler angles in its own order, radians: (F, J, 3)."""
    rot, _ = local_rotations(skel, torch.from_numpy(bvh.motion[frames]), bvh.channels)
    return torch.stack(
        [
            matrix_to_euler(rot[:, j], skel.rotation_orders[j] or "ZYX")
            for j in range(skel.num_joints)
        ],
        1,
    )


def test_recorded_walk_is_within_the_bundled_limits_and_a_backward_knee_is_not():
    bvh = read_bvh(BUNDLED)
    skel = Skeleton.from_bvh(bvh)
    lim = limits_tensor(skel, load_limits("cmu_cgspeed"))
    angles = _angles(bvh, skel, slice(1, None))
    assert limit_violation(angles, lim).max() < 1e-6
    knee = skel.index("LeftLeg")
    bent = angles.clone()
    bent[:, knee, skel.rotation_orders[knee].index("X")] = math.radians(-40)
    viol = limit_violation(bent, lim)
    assert viol[:, knee].max() == pytest.approx(math.radians(25), abs=1e-6)
    # joints that never move in CMU data have no degree of freedom
    hip_offset = skel.index("LHipJoint")
    assert (lim[hip_offset, :, 0] == lim[hip_offset, :, 1]).all()
    assert torch.isinf(lim[0]).all()  # the root orientation is free


@requires_shared_data()
@pytest.mark.shared_data
def test_daz_limits_fit_their_skeletons():
    bvh = read_bvh(SHARED_DATA / "bvh" / "cmu_lawrennd_mocap" / "10_03.bvh")
    skel = Skeleton.from_bvh(bvh)
    lim = limits_tensor(skel, load_limits("cmu_daz"))
    assert limit_violation(_angles(bvh, skel, slice(0, None, 10)), lim).max() < 1e-6


def test_limits_errors():
    skel = Skeleton.from_bvh(read_bvh(BUNDLED))
    with pytest.raises(KeyError, match="no joint 'Tail'"):
        limits_tensor(skel, {"Tail": {"X": [0, 1]}})
