"""Every config runs in tiny mode (configs cannot drift from code); the metric names are a
contract (accuracy figures in metrics.json, timings in timings.json); config mistakes fail
loudly."""

import json
import math
from pathlib import Path

import pytest

from experiments.__main__ import main
from experiments.config import ConfigError, load_config, parse_overrides
from experiments.runner import EXPERIMENTS, run_config
from tests.conftest import SHARED_DATA, requires_shared_data

CONFIGS = sorted((Path(__file__).resolve().parents[2] / "experiments" / "configs").glob("*.yaml"))
CONTRACT = {  # metrics.json: accuracy figures (the same seed gives the same file)
    "stick_pose": [
        f"{p}{m}_{n}"
        for p in ("", "opencv_")
        for m in ("reg_err_mean", "rot_err_deg_mean", "pos_err_mean")
        for n in ("n0", "n18", "n36")
    ],
    "pose2sim_real": [
        "cam_rot_err_deg_mean",
        "cam_pos_err_m_mean",
        "reproj_px_median",
        "c_err_mean",
    ],
    "stick_time": [
        f"{m}_{method}"
        for m in ("c_err_mean", "c_err_outside_mean", "c_err_inside_mean")
        for method in ("dtw", "chain", "robust")
    ],
    "nbp_single_image": [
        "e2d_init_mean",
        "e2d_mean",
        "e3d_init_mean",
        "e3d_mean",
        "e3d_depth_oracle_mean",
    ],
    "nbp_noise_sweep": ["e2d_mean_at_0", "e3d_mean_at_0", "e2d_mean_at_30", "e3d_mean_at_30"],
    "nbp_ablation": ["e2d_mean_full", "e3d_mean_full", "e2d_mean_bpmc", "e3d_mean_bpmc"],
    "register_synthetic": [
        "c_err_mean",
        "c_err_mean_stage1",
        "t_rot_err_deg_mean",
        "t_pos_err_mean",
        "a_err_deg_mean",
        "a_err_deg_mean_no_change",
        "e3d_mean",
        "silhouette_iou_truth_mean",
        "silhouette_iou_no_change_mean",
    ],
    "register_long": ["c_err_mean", "c_err_mean_stage1", "a_err_deg_mean"],
    "stage1_draws": ["c_err_mean_stage1", "c_err_median_stage1", "c_far_fraction"],
    "polish_basin": [
        f"{m}_{start}"
        for m in ("angle_rms_deg_start", "angle_rms_deg_polished", "range_recovered")
        for start in ("truth", "none")
    ],
    "register_real": [
        "sports2d_silhouette_iou_mean",
        "pose2sim_silhouette_iou_mean",
        "pose2sim_e3d_mean",
        "pose2sim_rmse_deg_leg_flexion_mean",
        "pose2sim_rmse_deg_centred_leg_flexion_mean",
        "pose2sim_reference_rmse_deg_leg_flexion_mean",
        "pose2sim_own_rmse_deg_leg_flexion_mean",
    ],
}
TIMINGS_CONTRACT = {  # timings.json: what varies from run to run
    "stick_pose": ["poses_per_s", "opencv_poses_per_s"],
    "pose2sim_real": [],
    "stick_time": [],
    "nbp_single_image": ["sec_per_frame"],
    "nbp_noise_sweep": ["sec_per_frame"],
    "nbp_ablation": ["sec_per_frame_full"],
    "register_synthetic": ["sec_per_video_frame"],
    "register_long": ["sec_stage1", "sec_total", "peak_rss_mb"],
    "register_real": ["sports2d_sec", "pose2sim_sec"],
    "stage1_draws": ["sec_stage1"],
    "polish_basin": [],
}


def _same_record(written: dict, returned: dict) -> bool:
    """The record on disk is the one returned; NaN (a metric with nothing to measure, such
    as the agreement of findings when none is stated) equals NaN."""

    def same(a, b) -> bool:
        both_nan = isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
        return both_nan or a == b

    return written.keys() == returned.keys() and all(same(written[k], returned[k]) for k in written)


def _has(keys, key) -> bool:
    return any(k == key or k.startswith(key + "@") for k in keys)


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_every_config_runs_tiny_and_writes_its_record(path, tmp_path):
    needs_shared = (
        path.stem in ("pose2sim_real", "register_real") or "../shared" in path.read_text()
    )
    if needs_shared and not SHARED_DATA.is_dir():
        pytest.skip(f"needs the shared data folder at {SHARED_DATA}")
    metrics = run_config(path, {"tiny": True, "out_dir": str(tmp_path)})
    name = load_config(path, {k: v.schema for k, v in EXPERIMENTS.items()})[0]
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    timings_file = tmp_path / "timings.json"
    timings = json.loads(timings_file.read_text()) if timings_file.exists() else {}
    assert _same_record({**on_disk, **timings}, metrics) and (tmp_path / "table.md").exists()
    records = [p.parent for p in tmp_path.rglob("config.yaml")]  # the run, or a sweep's runs
    assert records and all(
        json.loads((r / "provenance.json").read_text())["commit"] for r in records
    )
    for key in CONTRACT[name]:
        assert _has(on_disk, key), key
    for key in TIMINGS_CONTRACT[name]:
        assert _has(timings, key) and not _has(on_disk, key), key
    assert list(tmp_path.rglob("plot.png")) and list(tmp_path.rglob("per_frame.csv"))


def test_stick_time_targets_on_the_default_config_tiny(tmp_path):
    m = run_config(
        CONFIGS[[c.stem for c in CONFIGS].index("stick_time")],
        {"tiny": True, "out_dir": str(tmp_path)},
    )
    assert m["c_err_mean_chain@corrupt=False"] <= 1.0
    assert m["c_err_outside_mean_robust@corrupt=True"] <= 1.0


def test_stick_pose_with_an_orthographic_camera(tmp_path):
    """OpenCV's PnP has no orthographic camera: only ours is reported, exact without noise."""
    m = run_config(
        CONFIGS[[c.stem for c in CONFIGS].index("stick_pose")],
        {"tiny": True, "out_dir": str(tmp_path), "camera": "orthographic"},
    )
    assert m["rot_err_deg_mean_n0"] < 1e-6 and m["pos_err_mean_n0"] < 1e-9
    assert 0 < m["rot_err_deg_mean_n18"] < m["rot_err_deg_mean_n36"] < 5
    assert not any(k.startswith("opencv_") for k in m)
    with pytest.raises(ConfigError, match="camera must be one of"):
        run_config(
            CONFIGS[[c.stem for c in CONFIGS].index("stick_pose")],
            {"tiny": True, "out_dir": str(tmp_path), "camera": "fisheye"},
        )


def test_config_mistakes_fail_loudly(tmp_path):
    schemas = {k: v[0] for k, v in EXPERIMENTS.items()}
    bad = tmp_path / "bad.yaml"
    bad.write_text("experiment: stick_time\ncorupt: true\n")
    with pytest.raises(ConfigError, match="unknown key 'corupt' for StickTimeConfig"):
        load_config(bad, schemas)
    bad.write_text("experiment: stick_time\nnoise: lots\n")
    with pytest.raises(ConfigError, match="noise must be a number"):
        load_config(bad, schemas)
    bad.write_text("experiment: stick_time\nsweep:\n  - {fsp: 30}\n")
    with pytest.raises(ConfigError, match=r"sweep\[0\]: unknown key 'fsp'"):
        load_config(bad, schemas)
    bad.write_text("experiment: nonsense\n")
    with pytest.raises(ConfigError, match="unknown experiment 'nonsense'"):
        load_config(bad, schemas)
    assert parse_overrides(["seed=3", "corrupt=false", "fps=30.0"]) == {
        "seed": 3,
        "corrupt": False,
        "fps": 30.0,
    }


def test_cli_run_reports_errors_in_one_line(tmp_path, capsys):
    assert main(["run", str(CONFIGS[0]), "colour=red"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "unknown key 'colour'" in err and "\n" not in err


@requires_shared_data()
@pytest.mark.shared_data
def test_pose2sim_real_meets_its_targets(tmp_path):
    """Extrinsics within a few degrees / centimetres of the calibration, C error <= 1 frame."""
    m = run_config(
        CONFIGS[[c.stem for c in CONFIGS].index("pose2sim_real")], {"out_dir": str(tmp_path)}
    )
    assert m["cam_rot_err_deg_mean"] < 3.0 and m["cam_pos_err_m_mean"] < 0.1
    assert m["c_err_mean"] <= 1.0 and m["reproj_px_median"] < 15


def test_missing_data_skips_only_at_the_default_location(tmp_path, capsys, monkeypatch):
    """The test suite's case: the default ../shared/data absent -> a skip with a message;
    a data folder the user names that lacks the trial -> an error."""
    from experiments import pose2sim_real

    path = CONFIGS[[c.stem for c in CONFIGS].index("pose2sim_real")]
    absent = tmp_path / "shared" / "data"
    monkeypatch.setattr(pose2sim_real, "SHARED", absent)
    assert main(["run", str(path), f"data={absent}", f"out_dir={tmp_path / 'o'}"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-1].startswith("skipped: pose2sim_real needs the shared data set")
    assert main(["run", str(path), f"data={tmp_path}", f"out_dir={tmp_path / 'o'}"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: data={tmp_path}: expected the shared data folder")
    assert err.count("\n") == 1


def test_stick_time_coarse_to_fine_matches_the_full_chain_without_the_full_matrix(tmp_path):
    from experiments.stick_time import StickTimeConfig, run

    base = StickTimeConfig(tiny=True, corrupt=False, out_dir=str(tmp_path))
    full, _, _ = run(StickTimeConfig(**{**base.__dict__, "methods": ["chain"]}))
    c2f, _, _ = run(
        StickTimeConfig(
            **{
                **base.__dict__,
                "methods": ["c2f"],
                "c2f_max_cells": 400,
                "full_matrix_max_cells": 1,
            }
        )
    )
    assert c2f["c_err_mean_c2f"] <= full["c_err_mean_chain"] + 0.05
    # corrupted input: the robust cost and slope prior work coarse-to-fine as on the full matrix
    bad = StickTimeConfig(**{**base.__dict__, "corrupt": True})
    full, _, _ = run(StickTimeConfig(**{**bad.__dict__, "methods": ["robust"]}))
    c2f, _, _ = run(
        StickTimeConfig(
            **{
                **bad.__dict__,
                "methods": ["c2f", "c2f_robust"],
                "c2f_max_cells": 400,
                "full_matrix_max_cells": 1,
            }
        )
    )
    assert c2f["c_err_outside_mean_c2f_robust"] <= full["c_err_outside_mean_robust"] + 0.25
    assert c2f["c_err_outside_mean_c2f_robust"] <= 1.0
    with pytest.raises(ValueError, match="use methods=\\[c2f\\] for long sequences"):
        run(StickTimeConfig(**{**base.__dict__, "full_matrix_max_cells": 1}))


def test_nbp_schema_defaults_are_the_shipped_config():
    """Experiments that build nbp_single_image runs from the schema (the sweep, the ablation)
    must run what nbp_single_image.yaml runs."""
    from experiments.config import load_config
    from experiments.nbp_single_image import NbpSingleImageConfig
    from experiments.runner import EXPERIMENTS

    schemas = {name: e.schema for name, e in EXPERIMENTS.items()}
    path = CONFIGS[[c.stem for c in CONFIGS].index("nbp_single_image")]
    shipped = load_config(path, schemas)[1]
    schema = NbpSingleImageConfig()
    for field in ("cues", "proposal", "particles", "iterations", "restarts", "noise_deg"):
        assert getattr(shipped, field) == getattr(schema, field), field


def test_register_real_writes_the_calibration_of_the_cameras_it_registers(tmp_path):
    from experiments.register_real import POSE2SIM_CALIBRATION, _calibration_of
    from motion.cameras import load_pose2sim_calibration

    path = SHARED_DATA / POSE2SIM_CALIBRATION
    if not path.is_file():
        pytest.skip(f"needs {path}")
    whole = load_pose2sim_calibration(path)
    for cameras in ([1], [2, 4]):
        part = load_pose2sim_calibration(_calibration_of(path, cameras, tmp_path))
        assert part.names == [f"cam_0{c}" for c in cameras]
        index = [c - 1 for c in cameras]
        assert (part.K == whole.K[index]).all() and (part.t == whole.t[index]).all()
