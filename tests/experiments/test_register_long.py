"""The long-video registration experiment: its chained reference runs on without a jump at
the seams, and its tiny config runs and writes its record."""

import csv
import json
import math
from pathlib import Path

import pytest
import torch

from experiments.register_long import chain_walk, heading, loop_phase_error
from experiments.runner import run_config
from experiments.stick_time import BUNDLED
from motion.bvh import read_bvh, write_bvh
from motion.kinematics import Skeleton, local_rotations
from motion.registration import Reference

CONFIG = Path(__file__).resolve().parents[2] / "experiments" / "configs" / "register_long.yaml"


def _steps(bvh):
    """Per-frame root position step (metres), heading step (degrees) and posture step (norm
    of the change of every other joint's rotation matrix) of a BVH's motion frames."""
    skeleton = Skeleton.from_bvh(bvh)
    rot, root = local_rotations(skeleton, torch.from_numpy(bvh.motion_frames()), bvh.channels)
    position = root.diff(dim=0).norm(dim=-1)
    turn = torch.rad2deg(heading(rot[:, 0])).diff().abs()
    turn = torch.minimum(turn, 360 - turn)  # across +-180 degrees
    posture = (rot[1:, 1:] - rot[:-1, 1:]).flatten(1).norm(dim=1)
    return position, turn, posture


@pytest.mark.parametrize("radius", [0.0, 2.0], ids=["straight", "circle"])
def test_chained_reference_has_no_jump_at_the_seams(radius):
    frames = 800  # three copies of the ~261-frame loop
    chained, facts = chain_walk(BUNDLED, frames, radius_m=radius)
    assert chained.motion_frames().shape[0] == frames
    seams = torch.tensor(facts["seams"])
    assert len(seams) == math.ceil(frames / facts["loop"]) - 1 >= 2
    position, turn, posture = _steps(chained)
    at = seams - 1  # the step from a copy's last frame into the next copy's first
    for name, step in (("root position", position), ("heading", turn), ("posture", posture)):
        typical = float(step.median())
        worst = float(step[at].max())
        assert worst <= 2 * typical, f"{name}: step {worst:.4g} at a seam, typical {typical:.4g}"
    # the clip itself has such steps everywhere: nothing above its own largest step
    clip_position, _, clip_posture = _steps(read_bvh(BUNDLED))
    assert float(position.max()) <= 1.05 * float(clip_position.max())
    assert float(posture.max()) <= 1.05 * float(clip_posture.max())


def test_chained_reference_walks_round_a_circle_and_reads_back(tmp_path):
    frames = 1500  # 12.5 s, about one lap of a 2 m circle
    chained, _ = chain_walk(BUNDLED, frames, radius_m=2.0)
    reference = Reference.from_bvh(write_bvh(chained, tmp_path / "chained.bvh"))
    assert reference.num_frames == frames
    floor = reference.root[:, [0, 2]]
    centre = floor.mean(0)
    spread = (floor - centre).norm(dim=-1)
    assert float(spread.max()) < 2.6  # stays on the track, never walks off
    straight, _ = chain_walk(BUNDLED, frames, radius_m=0.0)
    reach = Reference.from_bvh(write_bvh(straight, tmp_path / "straight.bvh")).root[:, [0, 2]]
    assert float((reach[-1] - reach[0]).norm()) > 10  # the unbent chain walks away


def test_tiny_config_runs_and_writes_its_metrics(tmp_path):
    metrics = run_config(CONFIG, {"tiny": True, "out_dir": str(tmp_path)})
    accuracy = json.loads((tmp_path / "metrics.json").read_text())
    timings = json.loads((tmp_path / "timings.json").read_text())
    for key in ("c_err_mean", "a_err_deg_mean", "c_err_mean_stage1", "c_phase_err_mean"):
        assert math.isfinite(accuracy[key]) and accuracy[key] >= 0, key
    for key in ("sec_stage1", "sec_total", "peak_rss_mb"):
        assert timings[key] > 0 and key not in accuracy, key
    assert timings["sec_stage1"] <= timings["sec_total"]
    assert accuracy["c_phase_err_mean"] <= accuracy["c_err_mean"]
    assert {**accuracy, **timings} == metrics
    with open(tmp_path / "per_frame.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == accuracy["num_video_frames"]
    assert {"c_true", "c", "c_err", "c_stage1"} <= set(rows[0])
    assert (tmp_path / "plot.png").stat().st_size > 0


def test_loop_phase_error_folds_whole_loops_away():
    error = torch.tensor([0, 3, -3, 261, 264, -258, 130, 131, -131, 5 * 261 + 7])
    expected = [0, 3, 3, 0, 3, 3, 130, 130, 130, 7]
    assert loop_phase_error(error, 261).tolist() == pytest.approx(expected)
