"""The findings' method error table (motion.registration.method_error) and how the finding
rules read it."""

from __future__ import annotations

import math

import pytest

from motion.registration import Reference
from motion.registration.export import (
    FALLBACK_METHOD_ERROR_DEG,
    FindingSettings,
    JointDifference,
)
from motion.registration.method_error import MethodError, shipped_method_error
from motion.registration.types import RegistrationError
from tests.motion.body.conftest import WALK

TABLE = MethodError(
    {1: {"knee_angle_l": 6.0, "hip_rotation_l": 20.0}, 2: {"knee_angle_l": 4.0}},
    "made up",
    {1: {"knee_angle_l": 100, "hip_rotation_l": 100}, 2: {"knee_angle_l": 50}},
)


def test_a_table_round_trips_through_its_file(tmp_path):
    path = TABLE.write(tmp_path / "sub" / "error.json")
    assert MethodError.read(path) == TABLE


def test_a_registration_reads_the_largest_camera_count_not_above_its_own():
    assert TABLE.error_deg("knee_angle_l", 1) == 6.0
    assert TABLE.error_deg("knee_angle_l", 2) == 4.0
    assert TABLE.error_deg("knee_angle_l", 4) == 4.0  # 4 cameras: the 2-camera calibration
    assert TABLE.error_deg("hip_rotation_l", 2) is None  # not calibrated with 2 cameras
    only_two = MethodError({2: {"knee_angle_l": 4.0}})
    assert only_two.error_deg("knee_angle_l", 1) == 4.0  # below every count: the smallest


@pytest.mark.parametrize(
    ("degrees", "message"),
    [
        ({}, "at least one camera count"),
        ({0: {"knee_angle_l": 1.0}}, "camera counts must be integers >= 1; got 0"),
        ({1: {"knee_angle_l": -1.0}}, r"finite and >= 0 degrees; got \{'knee_angle_l': -1.0\}"),
        ({1: {"knee_angle_l": math.nan}}, "finite and >= 0 degrees"),
    ],
)
def test_a_bad_table_is_refused(degrees, message):
    with pytest.raises(RegistrationError, match=message):
        MethodError(degrees)


def test_a_file_that_is_no_table_names_itself(tmp_path):
    path = tmp_path / "error.json"
    path.write_text('{"degrees": [1, 2]}')
    with pytest.raises(RegistrationError, match=r"error.json: not a method error table"):
        MethodError.read(path)


def test_the_rules_take_a_number_or_the_table_and_fall_back_for_an_uncovered_coordinate():
    assert FindingSettings(method_error_deg=3.0).method_error("knee_angle_l", 1, TABLE) == 3.0
    calibrated = FindingSettings(max_interval_deg=None)
    assert calibrated.method_error("knee_angle_l", 2, TABLE) == 4.0
    assert calibrated.method_error("elbow_flex_r", 1, TABLE) == FALLBACK_METHOD_ERROR_DEG
    # -15 is clear of 2 x 6 (the knee with one camera), not of 2 x 20 (a hip's rotation)
    knee = JointDifference("knee_angle_l", -15.0, 1.0, 1.5, 6.0, uncertainty_deg=0.5, frames=13)
    assert calibrated.why_not(knee, 25.0, 1, TABLE) == ""
    # by default a finding's interval must also be within +- 5: +- 12 is not
    assert (
        FindingSettings()
        .why_not(knee, 25.0, 1, TABLE)
        .startswith("its interval (-15 ± 12 degrees) is wider than ± 5")
    )
    assert FindingSettings().why_not(knee, 25.0, 2, MethodError({2: {"knee_angle_l": 2.0}})) == ""
    hip = JointDifference("hip_rotation_l", -15.0, 1.0, 1.5, 6.0, uncertainty_deg=0.5, frames=13)
    assert calibrated.why_not(hip, 25.0, 1, TABLE) == (
        "its interval (-15 ± 40 degrees; the inference's ± 0 and the method's error of 20 "
        "degrees) holds 0: the inference cannot tell it from no difference"
    )


def test_the_shipped_table_covers_every_coordinate_the_bundled_walk_estimates():
    """Measured with 1 and 2 cameras, each coordinate a finite error of at least half a
    degree (no registration of another performer is exact) from many frames."""
    from motion.registration.export import _estimated_coordinates, _segments

    reference = Reference.from_bvh(WALK)
    segments = _segments(reference)
    from motion.angles import COORDINATES

    estimated = [
        c
        for c, e in zip(COORDINATES, _estimated_coordinates(reference, segments), strict=True)
        if e
    ]
    table = shipped_method_error()
    assert sorted(table.degrees) == [1, 2]
    for cameras in (1, 2):
        for name in estimated:
            error = table.error_deg(name, cameras)
            assert error is not None and 0.5 <= error < 90, (name, cameras, error)
            assert table.frames[cameras][name] >= 100
