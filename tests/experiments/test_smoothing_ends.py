"""experiments.smoothing_ends: scores whose values are known by construction (a root moving
at a steady speed, one registered 10 % short), and the page refusing runs already smoothed."""

from __future__ import annotations

import csv
import json
import math

import pytest
import torch
import yaml

from experiments.smoothing_ends import main, page, score_root, smoothed_root

FPS = 25.0


def _steady(frames: int = 50, speed: float = 1.2) -> torch.Tensor:
    """(frames, 3) a root walking along x at ``speed`` m/s, 0.9 m up."""
    t = torch.arange(frames, dtype=torch.float64) / FPS
    return torch.stack([speed * t, torch.full_like(t, 0.9), torch.zeros_like(t)], 1)


def test_a_root_registered_short_of_its_travel_scores_its_shortfall():
    truth = _steady()
    assert score_root(truth, truth, FPS).net_err_pct == 0.0
    short = truth.clone()
    short[:, 0] *= 0.9  # every displacement 10 % short, the speed too
    score = score_root(short, truth, FPS)
    assert score.net_err_pct == pytest.approx(-10.0, abs=1e-9)
    assert score.peak_err_pct == pytest.approx(-10.0, abs=1e-9)
    # the error grows along the path, 0.12 m/s x t: both ends together average what the
    # middle does, 0.12 x 24.5 frames / 25 fps
    assert score.end_err_m == pytest.approx(0.1176) and score.inside_err_m == pytest.approx(0.1176)
    standing = _steady(speed=0.0)
    assert math.isnan(score_root(standing, standing, FPS).net_err_pct)  # nothing travels


def test_the_weighted_mean_registers_a_steady_walk_short_and_the_line_does_not():
    truth = _steady()
    line = score_root(smoothed_root(truth, FPS, "linear"), truth, FPS)
    assert abs(line.net_err_pct) < 1e-9 and line.end_err_m < 1e-12
    mean = score_root(smoothed_root(truth, FPS, "constant"), truth, FPS)
    # each end lags by about 0.8 sigma (2.5 frames at 0.1 s) less its end window's own lag
    assert -8.0 < mean.net_err_pct < -2.0 and mean.inside_err_m < 1e-12
    assert torch.equal(smoothed_root(truth, FPS, "unsmoothed"), truth)


def _record(folder, registration: dict) -> None:
    folder.mkdir(parents=True)
    config = {"experiment": "register_synthetic", "fps": FPS, "student": "s.bvh", "warp_seed": 0}
    config["registration"] = registration
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    (folder / "metrics.json").write_text(json.dumps({"c_err_mean": 1.0}))
    truth = _steady()
    with open(folder / "per_frame.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", *(f"root_{a}" for a in "xyz"), *(f"root_true_{a}" for a in "xyz")])
        for i, p in enumerate(truth.tolist()):
            w.writerow([i, *p, *p])


def test_the_page_reads_unsmoothed_runs_and_refuses_smoothed_ones(tmp_path, capsys):
    _record(tmp_path / "raw" / "a", {"refine.smooth_s": "0"})
    text = page([str(tmp_path / "raw")])
    assert "| s, warp seed 0 | +0.0 | +0.0 |" in text  # unsmoothed, linear: exact
    _record(tmp_path / "smoothed" / "a", {})
    assert main([str(tmp_path / "smoothed")]) == 2
    assert "registered with the final smoothing on" in capsys.readouterr().err
