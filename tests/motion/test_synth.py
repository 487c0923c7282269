"""Synthetic sequences: ground truth is self-consistent and the CLI writes the documented format."""

import json

import numpy as np
import pytest
import torch

from motion.__main__ import main
from motion.cameras import CameraRig
from motion.synth import SynthConfig, SynthConfigError, load_sequence, save_sequence, synthesize
from tests.conftest import SHARED_DATA, requires_shared_data
from tests.motion.test_bvh import BUNDLED


@pytest.fixture(scope="module")
def sequence():
    cfg = SynthConfig(
        cameras=2,
        size=[64, 48],
        focal_px=120,
        articulation={"LeftLeg": 20, "RightArm": 30},
        yaw_deg=40,
        path_m=[0.5, 0.0, 0.0],
        body_scale=1.1,
        replace=[0.4, 0.5],
        noise_px=2.0,
        seed=3,
    )
    return synthesize(BUNDLED, cfg)


def test_reprojecting_true_3d_joints_gives_the_stored_2d_joints(sequence):
    a = sequence.arrays
    c = a["K"].shape[0]
    rig = CameraRig(
        torch.from_numpy(a["K"]),
        torch.from_numpy(a["R"]),
        torch.from_numpy(a["t"]),
        torch.zeros(c, 5, dtype=torch.float64),
        torch.tensor([[64, 48]] * c, dtype=torch.float64),
        sequence.meta["cameras"],
    )
    uv, depth = rig.project(torch.from_numpy(a["joints3d"]))
    np.testing.assert_allclose(uv.transpose(0, 1).numpy(), a["joints2d"], atol=1e-9)
    assert (depth > 0).all()
    noise = a["joints2d_noisy"] - a["joints2d"]
    assert abs(noise.std() - 2.0) < 0.1


def test_time_warp_is_monotone_smooth_and_spans_the_reference(sequence):
    a, m = sequence.arrays, sequence.meta
    c = a["C_true"]
    assert c[0] == 0 and c[-1] == m["num_reference_frames"] - 1
    steps = np.diff(c)
    nominal = m["reference_rate_hz"] / m["video_rate_hz"]
    assert steps.min() >= 0 and steps.max() <= np.ceil(nominal * 1.3) + 1  # speed within 1 +- 0.3
    assert steps.std() > 0.2  # non-linear
    rep = a["replaced"]
    assert rep.sum() == int(0.5 * len(c)) - int(0.4 * len(c))
    assert (a["C_shown"][~rep] == c[~rep]).all() and (a["C_shown"][rep] > c[rep]).all()


def test_articulation_body_size_and_images_are_consistent(sequence):
    a = sequence.arrays
    names = sequence.meta["joint_names"]
    leg = names.index("LeftLeg")
    assert np.abs(a["A_deg"][:, leg]).max() <= 20 + 1e-9 and np.abs(a["A_deg"][:, leg]).max() > 5
    assert np.abs(a["A_deg"][:, names.index("Head")]).max() == 0
    assert (a["silhouettes"] == (a["labels"] >= 0)).all()
    assert a["silhouettes"].mean() > 0.02
    assert a["edges"].any() and a["frames"].dtype == np.uint8
    # the pelvis projects onto the silhouette in (nearly) every frame it is inside the image
    uv = np.round(a["joints2d"][:, :, 0]).astype(int)
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < 64) & (uv[..., 1] >= 0) & (uv[..., 1] < 48)
    cams, frames = np.nonzero(inside)
    on = a["silhouettes"][cams, frames, uv[cams, frames, 1], uv[cams, frames, 0]]
    assert on.mean() > 0.95


def test_save_and_load_round_trip(sequence, tmp_path):
    save_sequence(sequence, tmp_path)
    back = load_sequence(tmp_path)
    assert back.meta == json.loads(json.dumps(sequence.meta))
    for k, v in sequence.arrays.items():
        assert np.array_equal(back.arrays[k], v), k


@requires_shared_data()
@pytest.mark.shared_data
def test_a_different_performer_as_the_student():
    seq = synthesize(
        BUNDLED,
        SynthConfig(size=[32, 24], focal_px=60),
        student=SHARED_DATA / "bvh" / "cmu_cgspeed" / "07_01.bvh",
    )
    assert (seq.arrays["C_true"] == -1).all()  # no ground-truth correspondence across performers
    assert seq.meta["student"].endswith("07_01.bvh")


def test_cli_synth_and_its_errors(tmp_path, capsys):
    out = tmp_path / "seq"
    assert (
        main(
            [
                "synth",
                "--reference",
                str(BUNDLED),
                "--out",
                str(out),
                "size=32x24",
                "focal_px=60",
                "fps=30",
                "articulation=LeftArm:10",
                "replace=0.4,0.5",
                "videos=true",
            ]
        )
        == 0
    )
    meta = json.loads((out / "sequence.json").read_text())
    assert meta["video_rate_hz"] == 30.0 and (out / "cam1.avi").exists()
    assert main(["synth", "--reference", str(BUNDLED), "--out", str(out), "colour=red"]) == 2
    assert "unknown setting 'colour'" in capsys.readouterr().err
    assert main(["synth", "--reference", str(BUNDLED), "--out", str(out), "warp=1.5"]) == 2
    assert "warp must be in [0, 1)" in capsys.readouterr().err
    assert main(["synth", "--reference", str(tmp_path / "none.bvh"), "--out", str(out)]) == 2


def test_a_sequence_with_videos_carries_its_calibration(tmp_path):
    """videos=true writes the cameras beside the videos (Pose2Sim TOML, listed by
    sequence_files), and the file reads back as the rig the sequence was rendered with."""
    from motion.cameras import load_pose2sim_calibration
    from motion.registration.inputs import sequence_cameras
    from motion.synth import CALIBRATION_FILE, sequence_files

    cfg = SynthConfig(cameras=2, size=[32, 24], focal_px=60, fps=5, videos=True, seed=1)
    seq = synthesize(BUNDLED, cfg)
    save_sequence(seq, tmp_path)
    files = sequence_files(seq.meta, tmp_path)
    assert files[-1] == tmp_path / CALIBRATION_FILE
    assert all(f.is_file() for f in files)
    back = load_pose2sim_calibration(tmp_path / CALIBRATION_FILE)
    want = sequence_cameras(seq, torch.float64)
    assert back.names == want.names == ["cam1", "cam2"]
    for key in ("K", "R", "t", "dist", "size"):
        torch.testing.assert_close(getattr(back, key), getattr(want, key), rtol=1e-9, atol=1e-12)
    no_videos = synthesize(BUNDLED, SynthConfig(size=[32, 24], focal_px=60, fps=5))
    assert all(f.suffix in (".npz", ".json") for f in sequence_files(no_videos.meta, tmp_path))


def test_the_first_frames_alone_are_the_whole_videos_first_frames():
    """``frames=n`` renders only the first n frames, and they are exactly the whole video's
    (the warp, the draws and the cameras are the whole motion's); ``images=False`` gives the
    same poses and joints without rendering."""
    cfg = SynthConfig(cameras=2, size=[64, 48], fps=12, articulation={"LeftLeg": 20.0})
    whole = synthesize(BUNDLED, cfg)
    cut = synthesize(BUNDLED, cfg, frames=5)
    bare = synthesize(BUNDLED, cfg, images=False)
    assert set(cut.arrays) == set(whole.arrays)
    assert set(whole.arrays) - set(bare.arrays) == {"silhouettes", "labels", "edges", "frames"}
    by_camera = {"joints2d", "joints2d_noisy", "silhouettes", "labels", "edges", "frames"}
    for key, array in whole.arrays.items():
        if key in ("K", "R", "t"):
            expected = array
        else:
            expected = array[:, :5] if key in by_camera else array[:5]
        assert np.array_equal(cut.arrays[key], expected), key
        if key in bare.arrays:
            assert np.array_equal(bare.arrays[key], array), key
    assert cut.meta["num_video_frames"] == 5 and cut.meta["shapes"]["frames"][1] == 5


def test_only_the_frames_drawn_count_against_the_image_memory_bound():
    """1,000 fps at 4096 x 4096 px would take some 1,000 GiB of images: refused whole, while
    its poses alone (``images=False``) cost nothing to draw."""
    cfg = SynthConfig(fps=1000, size=[4096, 4096])
    with pytest.raises(SynthConfigError, match=r"x 2850 frames x size=4096x4096"):
        synthesize(BUNDLED, cfg)
    with pytest.raises(SynthConfigError, match=r"x 300 frames x size=4096x4096"):
        synthesize(BUNDLED, cfg, frames=300)
    bare = synthesize(BUNDLED, cfg, images=False)
    assert bare.arrays["joints3d"].shape[0] == 2850 and "frames" not in bare.arrays
