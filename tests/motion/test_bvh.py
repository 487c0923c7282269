"""BVH reader: every shared file reads with the documented sizes; malformed files fail clearly."""

from pathlib import Path

import numpy as np
import pytest

from motion.bvh import BVHError, read_bvh, write_bvh
from tests.conftest import SHARED_DATA, requires_shared_data

BUNDLED = Path(__file__).resolve().parents[2] / "motion" / "data" / "cmu_02_01_walk.bvh"

# (file, frames, joints, channels) from ../shared/data/README.md
SHARED_FILES = [
    ("cmu_cgspeed/02_01.bvh", 344, 31, 96),
    ("cmu_cgspeed/07_01.bvh", 317, 31, 96),
    ("cmu_cgspeed/02_03.bvh", 174, 31, 96),
    ("cmu_cgspeed/09_01.bvh", 149, 31, 96),
    ("cmu_cgspeed/02_04.bvh", 484, 31, 96),
    ("cmu_cgspeed/01_01.bvh", 2752, 31, 96),
    ("cmu_cgspeed/05_02.bvh", 1124, 31, 96),
    ("cmu_cgspeed/06_15.bvh", 546, 31, 96),
    ("cmu_lawrennd_mocap/10_01.bvh", 802, 43, 132),
    ("cmu_lawrennd_mocap/10_03.bvh", 363, 43, 132),
    ("cmu_salsa_scaled/60_10_scaled.bvh", 1197, 43, 132),
    ("cmu_salsa_scaled/61_10_scaled.bvh", 1197, 43, 132),
]


def test_bundled_walk():
    bvh = read_bvh(BUNDLED)
    assert bvh.motion.shape == (344, 96)
    assert len(bvh.names) == 31 and bvh.names[0] == "Hips"
    assert bvh.parents[0] == -1 and (bvh.parents[1:] < np.arange(1, 31)).all()
    assert bvh.frame_rate == pytest.approx(120.0, rel=1e-4)
    assert len(bvh.rotation_columns()) == 93


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize(("name", "frames", "joints", "channels"), SHARED_FILES)
def test_every_shared_file_reads(name, frames, joints, channels):
    bvh = read_bvh(SHARED_DATA / "bvh" / name)
    assert bvh.motion.shape == (frames, channels)
    assert len(bvh.names) == joints
    assert np.isfinite(bvh.motion).all()


GOOD = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 1.5e1 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 2 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
1 2 3 4 5 6 7 8 9
1 2 3 4 5 6 7 8 9
"""


def _write(tmp_path, text, newline="\n"):
    p = tmp_path / "m.bvh"
    p.write_bytes(text.replace("\n", newline).encode())
    return p


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_small_file_with_exponents_and_crlf(tmp_path, newline):
    bvh = read_bvh(_write(tmp_path, GOOD, newline))
    assert bvh.names == ["Hips", "Spine"]
    assert bvh.offsets[1].tolist() == [0.0, 15.0, 0.0]
    assert bvh.end_sites[1].tolist() == [0.0, 2.0, 0.0]
    assert bvh.channels[0][3:] == ["Zrotation", "Xrotation", "Yrotation"]
    assert bvh.motion.shape == (2, 9)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.rsplit("1 2 3", 1)[0], r"m\.bvh:\d+: MOTION declares 2 frames but 1 rows"),
        (
            lambda t: t.replace("7 8 9\n1", "7 8\n1", 1),
            r"m\.bvh:19: frame 0 has 8 values; the hierarchy declares 9",
        ),
        (
            lambda t: t.replace("  }\n}\nMOTION", "  }\nMOTION"),
            r"m\.bvh:\d+: MOTION before all joint blocks are closed",
        ),
        (lambda t: t.replace("4 5 6", "4 nan 6", 1), r"m\.bvh:19: frame 0: non-finite value"),
        (
            lambda t: t.replace(
                "Zrotation Xrotation Yrotation\n    End", "Zrotation Xrotation Wrotation\n    End"
            ),
            r"m\.bvh:9: unknown channel name 'Wrotation'",
        ),
        (lambda t: t.replace("HIERARCHY", "HIERARCH"), r"m\.bvh:1: expected 'HIERARCHY'"),
        (lambda t: t.split("MOTION")[0], r"no MOTION block"),
    ],
    ids=["truncated", "short-row", "unbalanced", "nan", "channel", "header", "no-motion"],
)
def test_malformed_files_name_file_and_line(tmp_path, edit, message):
    with pytest.raises(BVHError, match=message):
        read_bvh(_write(tmp_path, edit(GOOD)))


def _same(a, b):
    assert a.names == b.names and a.channels == b.channels
    assert np.array_equal(a.parents, b.parents) and np.array_equal(a.offsets, b.offsets)
    assert a.end_sites.keys() == b.end_sites.keys()
    assert all(np.array_equal(a.end_sites[k], b.end_sites[k]) for k in a.end_sites)
    assert a.frame_time == b.frame_time and np.array_equal(a.motion, b.motion)


def test_round_trip_bundled(tmp_path):
    a = read_bvh(BUNDLED)
    _same(a, read_bvh(write_bvh(a, tmp_path / "out.bvh")))


@requires_shared_data()
@pytest.mark.shared_data
@pytest.mark.parametrize("name", [f for f, *_ in SHARED_FILES if "01_01" not in f])
def test_round_trip_every_shared_file(tmp_path, name):
    a = read_bvh(SHARED_DATA / "bvh" / name)
    _same(a, read_bvh(write_bvh(a, tmp_path / "out.bvh")))


def test_cgspeed_reference_pose_is_recognised():
    bvh = read_bvh(BUNDLED)
    assert bvh.has_reference_pose()
    assert bvh.motion_frames().shape == (343, 96)
    np.testing.assert_array_equal(bvh.motion_frames(), bvh.motion[1:])


@requires_shared_data()
@pytest.mark.shared_data
def test_daz_files_have_no_reference_pose():
    bvh = read_bvh(SHARED_DATA / "bvh" / "cmu_lawrennd_mocap" / "10_03.bvh")
    assert not bvh.has_reference_pose() and bvh.motion_frames().shape[0] == 363
