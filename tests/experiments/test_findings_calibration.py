"""The findings' calibration (experiments.findings_calibration): errors whose RMS is known by
construction, pairs left out, and the findings a table lets through."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from experiments.findings_calibration import (
    PELVIS,
    AngleRun,
    calibrate,
    error_parts,
    finding_errors,
    leave_pair_out,
    main,
    pelvis_rows,
    read_angle_run,
    score_run,
)
from experiments.register_synthetic import angle_columns
from motion.angles import COORDINATES, SegmentMap, clinical_angles
from motion.bundled import WALK_02_01
from motion.registration import Reference
from motion.registration.export import FindingSettings, JointAngles
from motion.registration.method_error import MethodError

NAMES = ["knee_angle_l", "hip_rotation_l"]
T = 20  # frames at 25 Hz


def make_run(pair, cameras, knee_error, hip_error, knee_truth=0.0, trusted=None) -> AngleRun:
    """A run whose estimated knee difference is the truth plus ``knee_error`` (a constant or
    a (T,) array), the hip's likewise; frames not ``trusted`` carry an error of 90."""
    truth = np.zeros((T, 2))
    truth[:, 0] = knee_truth
    estimate = truth + np.stack([np.broadcast_to(knee_error, T), np.broadcast_to(hip_error, T)], 1)
    trusted = np.ones(T, bool) if trusted is None else trusted
    estimate[~trusted] = 90.0
    return AngleRun(
        folder=Path("."),
        pair=pair,
        cameras=cameras,
        motions_match=True,
        coordinates=list(NAMES),
        time_s=np.arange(T) / 25.0,
        trusted=trusted,
        estimate=estimate,
        truth=truth,
        uncertainty=np.full((T, 2), 0.5),
    )


def test_the_error_is_the_rms_over_trusted_frames_per_camera_count():
    """Knee +3 everywhere and a hip alternating +-4 give RMS 3 and 4 exactly; untrusted
    frames (error 90) are left out; each camera count has its own table."""
    alternating = np.where(np.arange(T) % 2 == 0, 4.0, -4.0)
    half = np.arange(T) < T // 2
    runs = [
        make_run(("a.bvh", "b.bvh"), 1, 3.0, alternating, trusted=half | (np.arange(T) % 3 == 0)),
        make_run(("b.bvh", "a.bvh"), 1, -3.0, 4.0),
        make_run(("a.bvh", "b.bvh"), 2, 1.0, 2.0),
    ]
    table = calibrate(runs, "test")
    assert table.degrees[1] == pytest.approx({"knee_angle_l": 3.0, "hip_rotation_l": 4.0})
    assert table.degrees[2] == pytest.approx({"knee_angle_l": 1.0, "hip_rotation_l": 2.0})
    trusted_first = int((half | (np.arange(T) % 3 == 0)).sum())
    assert table.frames[1]["knee_angle_l"] == trusted_first + T
    assert table.source == "test"


def test_the_error_splits_into_the_timing_part_and_the_posture_part():
    """A knee estimated 6 too high where the reference's angle at the registration's C is 8
    below its angle at the true C (timing +8, posture -2: total +6) and a hip whose timing
    part alternates +-3 under a posture error of +4: the parts' RMS are those by
    construction; a run without its timing error is left out; untrusted frames too."""
    alternating = np.where(np.arange(T) % 2 == 0, 3.0, -3.0)
    timing = np.stack([np.full(T, 8.0), alternating], 1)
    trusted = np.arange(T) >= 2
    known = dataclasses.replace(
        make_run(("a", "b"), 1, 6.0, 4.0 + alternating, trusted=trusted), timing_error=timing
    )
    unknown = make_run(("a", "b"), 1, 50.0, 50.0)  # no timing error: not counted
    parts = error_parts([known, unknown])
    knee, hip = parts[1]["knee_angle_l"], parts[1]["hip_rotation_l"]
    assert (knee.total, knee.timing, knee.posture) == pytest.approx((6.0, 8.0, 2.0))
    assert (hip.timing, hip.posture) == pytest.approx((3.0, 4.0))
    assert hip.total == pytest.approx(5.0)  # +4 +- 3 alternating: sqrt((49 + 1) / 2)
    assert knee.frames == int(trusted.sum())


def test_one_shared_pelvis_tilt_leaves_the_trunk_to_thigh_angle_right():
    """Posture errors of +10 on lumbar extension and both hips (one pelvis tilt) give means
    of +10, a hip RMS of 10 and a trunk-to-thigh RMS of 0; a hip of its own (+10 against a
    lumbar 0) shows in the trunk-to-thigh angle."""
    zeros = np.zeros((T, 3))

    def run(pair, lumbar, hips):
        return AngleRun(
            folder=Path("."),
            pair=pair,
            cameras=1,
            motions_match=True,
            coordinates=list(PELVIS),
            time_s=np.arange(T) / 25.0,
            trusted=np.ones(T, bool),
            estimate=zeros + np.array([lumbar, hips, hips]),
            truth=zeros,
            uncertainty=zeros + 0.5,
            timing_error=zeros,
        )

    tilted, own = pelvis_rows([run(("a", "b"), 10.0, 10.0), run(("c", "d"), 0.0, 10.0)])
    assert (tilted.pair, tilted.cameras) == ("a against b", 1)
    assert tilted.means == pytest.approx([10.0, 10.0, 10.0])
    assert (tilted.hips_rms, tilted.trunk_thigh_rms) == pytest.approx((10.0, 0.0))
    assert (own.pair, own.hips_rms, own.trunk_thigh_rms) == ("c against d", 10.0, 10.0)


def test_a_record_with_its_c_reads_the_timing_error_from_its_reference(tmp_path):
    """The timing error read from a record's C columns is the bundled walk's clinical
    angles at the true C minus at the registration's C; with a reference that cannot be
    read it is none."""
    rows_c, rows_true = np.array([10, 40, 41]), np.array([12, 30, 41])
    names = ["knee_angle_r", "hip_flexion_l"]
    folder = _record(tmp_path, names, rows_c, rows_true)
    run = read_angle_run(folder, {"reference": str(WALK_02_01), "cameras": 1}, True)
    body = Reference.from_bvh(WALK_02_01)
    deg = clinical_angles(
        body.skeleton,
        body.rotations.double(),
        SegmentMap.from_roles(body.skeleton, body.model.mapping),
    ).degrees.numpy()[:, [COORDINATES.index(n) for n in names]]
    np.testing.assert_allclose(run.timing_error, deg[rows_true] - deg[rows_c], atol=1e-9)
    assert run.timing_error[2] == pytest.approx([0.0, 0.0])
    missing = read_angle_run(folder, {"reference": "no/such.bvh", "cameras": 1}, True)
    assert missing.timing_error is None


def test_a_findings_error_is_its_mean_difference_against_the_true_mean_over_its_frames():
    """Constant errors: the knee's finding errs by exactly its +10 / -10 in two runs (RMS
    10, bias 0), the hip's by +4 in one; a 2-camera run is counted apart."""
    runs = [
        make_run(("a", "b"), 1, 10.0, 4.0, knee_truth=3.0),
        make_run(("b", "a"), 1, -10.0, 0.0, knee_truth=-30.0),
        make_run(("a", "b"), 2, 6.0, 0.0, knee_truth=3.0),
    ]
    errors = finding_errors(runs)
    knee, hip = errors[1]["knee_angle_l"], errors[1]["hip_rotation_l"]
    assert (knee.count, knee.rms, knee.mean) == (2, pytest.approx(10.0), pytest.approx(0.0))
    assert (hip.count, hip.rms, hip.mean) == (1, pytest.approx(4.0), pytest.approx(4.0))
    assert errors[2]["knee_angle_l"].rms == pytest.approx(6.0)
    assert "hip_rotation_l" not in errors[2]  # no difference at all: no finding


def _record(folder: Path, names, c, c_true) -> Path:
    """A per_frame.csv with C columns and zero differences of ``names``."""
    columns = {"time_s": np.arange(len(c)) / 25.0, "trusted": np.ones(len(c), int)}
    columns |= {"c": c, "c_true": c_true}
    for name in names:
        columns |= {f"diff_{name}": np.zeros(len(c)), f"true_{name}": np.zeros(len(c))}
    with open(folder / "per_frame.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(list(columns))
        writer.writerows(zip(*columns.values(), strict=True))
    return folder


def test_a_pair_is_scored_with_the_table_of_the_other_pairs_alone():
    """The walk pair's runs (either direction) see the jog pair's errors, not their own."""
    runs = [
        make_run(("walk_a", "walk_b"), 1, 10.0, 10.0),
        make_run(("walk_b", "walk_a"), 1, 10.0, 10.0),
        make_run(("jog_a", "jog_b"), 1, 2.0, 5.0),
    ]
    tables = dict((id(run), table) for run, table in leave_pair_out(runs))
    for run in runs[:2]:
        assert tables[id(run)].degrees[1] == pytest.approx(
            {"knee_angle_l": 2.0, "hip_rotation_l": 5.0}
        )
    assert tables[id(runs[2])].degrees[1] == pytest.approx(
        {"knee_angle_l": 10.0, "hip_rotation_l": 10.0}
    )


def test_a_finding_is_stated_only_where_it_clears_the_table_and_is_scored_against_the_truth():
    """The student's knee truly flexes 20 degrees less (a difference of -20 in the knee's
    positive sense); estimated at -23 it agrees (within 5), and it is stated with a knee
    error of 4 (-23 clears 2 hypot(0.5, 4)) but not with 15."""
    run = make_run(("a", "b"), 1, -3.0, 0.0, knee_truth=-20.0)
    sure = MethodError({1: {"knee_angle_l": 4.0, "hip_rotation_l": 4.0}})
    wide = FindingSettings(max_interval_deg=None)  # -23 +- 8: stated without the +-5 bound
    score = score_run(run, wide, sure)
    assert score["findings_found"] == 1.0  # the hip's zero difference is no finding
    assert score["findings_stated"] == 1.0 and score["findings_agree_fraction"] == 1.0
    vague = MethodError({1: {"knee_angle_l": 15.0, "hip_rotation_l": 4.0}})
    score = score_run(run, wide, vague)
    assert score["findings_stated"] == 0.0 and math.isnan(score["findings_agree_fraction"])
    assert score["findings_withheld_fraction"] == 1.0
    assert score_run(run, FindingSettings(), sure)["findings_stated"] == 0.0  # +- 8 > +- 5
    fine = MethodError({1: {"knee_angle_l": 2.0, "hip_rotation_l": 4.0}})  # +- 4.1
    assert score_run(run, FindingSettings(), fine)["findings_stated"] == 1.0
    wrong = make_run(("a", "b"), 1, -9.0, 0.0, knee_truth=-20.0)  # stated, 9 off: disagrees
    score = score_run(wrong, FindingSettings(method_error_deg=0.0, max_interval_deg=None))
    assert score["findings_stated"] == 1.0 and score["findings_agree_fraction"] == 0.0


def test_a_record_written_by_register_synthetic_reads_back(tmp_path):
    """register_synthetic's per-frame columns (angle_columns) and config, read back by
    read_angle_run, then the command line writes a table and a page."""
    diff = torch.tensor([[1.0, -2.0], [3.0, 4.0], [5.0, 6.0]], dtype=torch.float64)
    truth = torch.zeros(3, 2, dtype=torch.float64)
    angles = JointAngles(
        coordinates=list(NAMES),
        time_s=torch.arange(3, dtype=torch.float64) / 25,
        reference_deg=diff,
        student_deg=diff,
        difference_deg=diff,
        articulation_deg=diff[:, 0],
        uncertainty_deg=torch.full((3, 2), 0.5, dtype=torch.float64),
    )
    columns = {"time_s": angles.time_s.numpy(), "trusted": np.array([1, 1, 0])}
    columns |= angle_columns(angles, truth)
    run_dir = tmp_path / "runs" / "one"
    run_dir.mkdir(parents=True)
    with open(run_dir / "per_frame.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(list(columns))
        writer.writerows(zip(*columns.values(), strict=True))
    config = {
        "experiment": "register_synthetic",
        "reference": "x/ref.bvh",
        "student": "y/stu.bvh",
        "cameras": 2,
    }
    (run_dir / "config.yaml").write_text(yaml.safe_dump(config))
    (run_dir / "metrics.json").write_text(json.dumps({"motions_match": 1.0}))
    run = read_angle_run(run_dir, config, True)
    assert run.pair == ("ref.bvh", "stu.bvh") and run.cameras == 2
    np.testing.assert_array_equal(run.trusted, [True, True, False])
    np.testing.assert_allclose(run.estimate, diff.numpy())
    np.testing.assert_allclose(run.uncertainty, 0.5)
    table_file, page_file = tmp_path / "error.json", tmp_path / "page.md"
    assert main([str(tmp_path / "runs"), "--write", str(table_file), "--to", str(page_file)]) == 0
    table = MethodError.read(table_file)
    assert table.degrees[2]["knee_angle_l"] == pytest.approx(math.sqrt((1 + 9) / 2))
    assert "| knee_angle_l | 2.2 (2) |" in page_file.read_text()
    assert main([str(tmp_path)]) == 2  # no record of another performer directly in it
