"""The definitions of the true C between two performers (experiments.truth_definitions):
each is zero where the postures are the same, each ignores what it claims to ignore, each is
checked against a direct computation, and the page reads run records."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
import torch
import yaml

from experiments.register_synthetic import (
    SyntheticStudentConfig,
    equally_true_alignments,
    truth_max_step,
)
from experiments.truth_definitions import (
    DISTANCES,
    PairTruths,
    bone_direction_distance,
    c_errors,
    difference_spread,
    local_rotation_distance,
    main,
    pair_truths,
    scaled_position_distance,
    truth_spread,
)
from motion.registration import Reference
from motion.synth import time_warp
from tests.motion.body.conftest import WALK


@pytest.fixture(scope="module")
def walk():
    return Reference.from_bvh(WALK)


def _shown(walk, seed=4):
    return time_warp(30, walk.num_frames - 60, 0.3, torch.Generator().manual_seed(seed)) + 20


def _resized(motion: Reference, factors: dict[str, float]) -> Reference:
    """``motion`` with the offsets of the named joints (and of their End Sites) multiplied."""
    offsets = motion.skeleton.offsets.clone()
    ends = dict(motion.skeleton.end_sites)
    for name, f in factors.items():
        j = motion.skeleton.index(name)
        offsets[j] = offsets[j] * f
        if j in ends:
            ends[j] = ends[j] * f
    skeleton = dataclasses.replace(motion.skeleton, offsets=offsets, end_sites=ends)
    return dataclasses.replace(motion, skeleton=skeleton)


@pytest.mark.parametrize("name", list(DISTANCES))
def test_the_same_motion_is_aligned_to_the_frames_it_shows_under_every_definition(walk, name):
    """A time-warped copy of the reference: each distance is 0 along the warp and positive
    off it, and the best alignment is the warp itself, the only truth."""
    shown = _shown(walk)
    cost = DISTANCES[name](walk, shown, walk)
    rows = torch.arange(len(shown))
    assert float(cost[rows, shown].abs().max()) < 1e-6
    assert float(cost[rows, shown + 15].min()) > 1e-3
    truths = equally_true_alignments(cost, truth_max_step(shown))
    assert torch.equal(truths[0], shown)


def test_bones_and_rotations_ignore_the_bones_lengths_and_positions_do_not(walk):
    """Longer thighs and shorter forearms: the same rotations give the same bone directions
    and local rotations, so those two distances are unchanged entry for entry; the joints'
    positions move, and the distance in metres no longer vanishes along the warp."""
    other = _resized(walk, {"LeftLeg": 1.2, "RightLeg": 1.2, "LeftHand": 0.8, "RightHand": 0.8})
    shown = _shown(walk)
    rows = torch.arange(len(shown))
    for distance in (bone_direction_distance, local_rotation_distance):
        # acos near 0: a rounding of 1e-16 in a cosine turns the angle by ~1e-6 degrees
        torch.testing.assert_close(
            distance(other, shown, walk), distance(walk, shown, walk), atol=1e-5, rtol=0
        )
    assert float(DISTANCES["positions"](other, shown, walk)[rows, shown].min()) > 0.005


def test_scaled_positions_ignore_the_size_of_the_whole_body(walk):
    """A body 1.25 times as large in every bone: the height-scaled distance is unchanged, the
    one in metres is not."""
    large = _resized(walk, {n: 1.25 for n in walk.skeleton.names})
    shown = _shown(walk)
    torch.testing.assert_close(
        scaled_position_distance(large, shown, walk), scaled_position_distance(walk, shown, walk)
    )
    rows = torch.arange(len(shown))
    assert float(DISTANCES["positions"](large, shown, walk)[rows, shown].min()) > 0.01


def test_the_bone_distance_is_the_mean_angle_between_the_bones_computed_one_by_one(walk):
    """One pair of frames, by a loop over the joints in NumPy."""
    shown = torch.tensor([10, 50])
    cost = bone_direction_distance(walk, shown, walk)
    a = walk.body_frames(shown).positions.numpy()
    b = walk.body_frames(torch.tensor([90])).positions.numpy()[0]
    parents = walk.skeleton.parents.tolist()
    angles = []
    for j, p in enumerate(parents):
        if p < 0 or float(walk.skeleton.offsets[j].norm()) <= 1e-9:
            continue
        u, v = a[1, j] - a[1, p], b[j] - b[p]
        cos = u @ v / np.linalg.norm(u) / np.linalg.norm(v)
        angles.append(math.degrees(math.acos(min(1.0, max(-1.0, cos)))))
    assert float(cost[1, 90]) == pytest.approx(np.mean(angles), abs=1e-6)


def test_the_rotation_distance_is_the_mean_turn_between_the_joints_rotations(walk):
    """Every rotating joint turned by a known angle about its own axis: the distance is the
    mean of those angles."""
    shown = torch.tensor([0])
    student = dataclasses.replace(walk, rotations=walk.rotations.clone())
    rotating = [
        j
        for j in range(walk.skeleton.num_joints)
        if int(walk.skeleton.parents[j]) >= 0 and walk.skeleton.rotation_orders[j]
    ]
    turns = torch.linspace(5.0, 40.0, len(rotating), dtype=torch.float64)
    for j, deg in zip(rotating, turns, strict=True):
        axis = torch.nn.functional.normalize(
            torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64), dim=0
        )
        k = torch.tensor(
            [[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]],
            dtype=torch.float64,
        )
        student.rotations[0, j] = student.rotations[0, j] @ torch.linalg.matrix_exp(
            math.radians(float(deg)) * k
        )
    cost = local_rotation_distance(student, shown, walk)
    assert float(cost[0, 0]) == pytest.approx(float(turns.mean()), abs=1e-6)


def test_the_difference_spread_is_the_reference_angle_between_the_two_truths():
    """A coordinate that ramps 2 degrees per reference frame and a definition 3 frames later
    than the experiment's truth: its true differences change by 2 x 3 = 6 degrees in every
    frame (the reference's angle at the experiment's C minus at the later one: -6); across
    +-180 the change wraps; the experiment's own definition changes nothing. Of two
    equally true alignments of the experiment, the nearer one is the anchor."""
    frames = torch.arange(40, dtype=torch.float64)
    angles = torch.stack([2.0 * frames, torch.where(frames < 22, 179.0, -179.0)], 1)
    ours = torch.stack([torch.arange(5) + 10, torch.arange(5) + 30])
    truths = PairTruths(
        "s.bvh",
        "r.bvh",
        0,
        {"positions": ours, "local_rotations": (torch.arange(5) + 13)[None]},
        angles,
    )
    spread = difference_spread(truths)
    torch.testing.assert_close(spread["positions"], torch.zeros(5, 2, dtype=torch.float64))
    torch.testing.assert_close(spread["local_rotations"][:, 0], torch.full((5,), -6.0).double())
    # frames 10..14 against 13..16: 179 - 179 = 0 before 22, and none cross it here
    torch.testing.assert_close(spread["local_rotations"][:, 1], torch.zeros(5).double())
    crossing = PairTruths(
        "s.bvh",
        "r.bvh",
        0,
        {"positions": (torch.arange(5) + 18)[None], "x": (torch.arange(5) + 20)[None]},
        angles,
    )
    # frame 18 vs 20: 179 - 179; 20 vs 22: 179 - (-179) = 358, wrapped -2; 22 vs 24: 0
    torch.testing.assert_close(
        difference_spread(crossing)["x"][:, 1], torch.tensor([0.0, 0.0, -2.0, -2.0, 0.0]).double()
    )


def _record(folder, config: dict, c, c_stage1) -> None:
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    (folder / "metrics.json").write_text(json.dumps({"c_err_mean": 0.0}))
    with open(folder / "per_frame.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["frame", "c", "c_stage1"])
        writer.writerows(zip(range(len(c)), c.tolist(), c_stage1.tolist(), strict=True))


def test_run_records_are_scored_against_every_definition_and_paged(tmp_path):
    """Another performer's synthetic student (subject 7's walk against subject 2's, 8 frames,
    small images): a record whose C is the experiment's truth scores 0 against it, one 3
    frames later 3; the reference's own student is skipped; a folder of none exits 2."""
    cfg = SyntheticStudentConfig(
        reference="motion/data/cmu_02_01_walk.bvh",
        student="motion/data/cmu_07_01_walk.bvh",
        frames=8,
        size=[80, 60],
        focal_px=112.5,
    )
    truths = pair_truths(cfg)
    assert set(truths.truths) == set(DISTANCES)
    assert all(t.shape[1] == 8 for t in truths.truths.values())
    assert truth_spread(truths)["positions"] == 0.0
    truth = truths.truths["positions"][0]
    assert c_errors(truth, truths)["positions"] == 0.0
    config = {"experiment": "register_synthetic", "seed": 0, **dataclasses.asdict(cfg)}
    _record(tmp_path / "runs" / "other", config, truth, truth + 3)
    _record(tmp_path / "runs" / "itself", {**config, "student": ""}, truth, truth)
    page = tmp_path / "page.md"
    figure = tmp_path / "truths.png"
    assert main([str(tmp_path / "runs"), "--to", str(page), "--figure", str(figure)]) == 0
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = page.read_text()
    spread, scored = [
        [c.strip() for c in line.split("|")[1:-1]]
        for line in text.splitlines()
        if line.startswith("| cmu_07_01_walk against")
    ]
    assert spread[:3] == ["cmu_07_01_walk against cmu_02_01_walk", "0", "0.0"]
    cells = scored
    assert cells[:4] == ["cmu_07_01_walk against cmu_02_01_walk", "1", "1", "0.00"]
    assert cells[8] == "3.00"  # stage 1's C against the experiment's truth
    assert "- runs: 2" in text
    empty = tmp_path / "none"
    _record(empty / "itself", {**config, "student": ""}, truth, truth)
    assert main([str(empty)]) == 2
