"""register() on a device (``RegistrationSettings.device``): the setting is checked when it is
made; every tensor the stages make follows the inputs' device, checked on any machine with
:class:`tests.device_probe.UnplacedOnMeta`; on a GPU (skipped without one, as in CI) the
result is as good as the CPU's."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import pytest
import torch

from motion.body.observation import Observation
from motion.cameras import CameraRig
from motion.devices import DeviceError, resolve_device, to_device
from motion.registration import RegistrationSettings, register
from motion.registration.approximate import Stage1Settings
from motion.registration.inputs import features_from_sequence
from motion.registration.pipeline import RegistrationSettingsError
from motion.registration.polish import PosturePolishSettings
from motion.registration.refine import RefineSettings
from motion.registration.types import Reference
from motion.synth import SynthConfig, synthesize
from tests.device_probe import UnplacedOnMeta
from tests.motion.registration.conftest import REFERENCE, STUDENT

#: every optional branch of the stages that makes tensors, at a cost of seconds: two cameras
#: (G measured), 2-D joints (the keypoint starts and cue, the proportions' fit), colour (the
#: intensity cue), several searches (the rendered choice among them), stage 3 and its
#: tempo alignment with fitted placements, the polish
BRANCHES = RegistrationSettings(
    stage1=Stage1Settings(
        yaw_starts=4,
        refine_starts=2,
        iterations=4,
        final_yaw_starts=4,
        final_iterations=6,
        scale_reference_frames=8,
        scale_rounds=1,
    ),
    refine=RefineSettings(
        particles=12,
        band=4,
        tempo_band=4,
        iterations=1,
        restarts=1,
        rounds=1,
        searches=2,
        window=8,
        overlap=2,
        tempo_placement="fitted",
    ),
    polish=PosturePolishSettings(steps=3, proportion_steps=3, proportion_frames=4),
)


@pytest.fixture(scope="module")
def two_views():
    """Another performer (CMU 07_01) against the bundled walk, 2 cameras, 10 frames."""
    config = SynthConfig(fps=25, cameras=2, size=[96, 72], focal_px=120)
    seq = synthesize(REFERENCE, config, student=STUDENT)
    video = features_from_sequence(seq, keypoints=True, image_dtype=torch.uint8)
    return seq, Reference.from_bvh(REFERENCE), video.cut(slice(0, 10))


def _same(a, b):
    for field in ("C", "C_stage1", "T_rotation", "T_translation", "A", "fit"):
        torch.testing.assert_close(getattr(a, field), getattr(b, field), rtol=0, atol=0)
    assert a.G == b.G
    torch.testing.assert_close(a.proportions.part_scales, b.proportions.part_scales)


def test_every_tensor_the_stages_make_follows_the_inputs_device(two_views):
    """Under :class:`UnplacedOnMeta` a tensor made in ``motion`` or ``pgm`` without
    ``device=`` lands on ``meta``, and the first operation beside the inputs' tensors (or
    reading it) fails: the run goes through and gives the plain run's result, bit for bit."""
    _, ref, video = two_views
    plain = register(ref, video, settings=BRANCHES)
    with UnplacedOnMeta(("motion", "pgm")):
        probed = register(ref, video, settings=BRANCHES)
    assert probed.G_measured and probed.proportions is not None  # the branches ran
    assert probed.C.device.type == "cpu"
    _same(plain, probed)


#: the other side of the branches: one camera (G not measured), a tree of a body graph (no
#: temporal edges: tree BP's schedule), no re-anchoring, no stage 3, the whole-body T and the
#: reference's twist off, frames where the person is unseen (carried by their neighbours)
OTHER_BRANCHES = RegistrationSettings(
    stage1=BRANCHES.stage1,
    refine=RefineSettings(
        particles=12,
        iterations=1,
        restarts=1,
        window=8,
        overlap=2,
        temporal=None,
        reanchor=False,
        refine_c=False,
        whole_body_t=False,
        twist_from_reference=False,
    ),
    polish=PosturePolishSettings(steps=3),
)


def test_the_other_branches_follow_the_inputs_device_too(two_views):
    _, ref, video = two_views
    one = video.cut(slice(0, 10))
    obs = one.observation
    silhouette = obs.silhouette[:, :, :1].clone()
    silhouette[:, 4:6] = 0.0  # unseen
    one = dataclasses.replace(
        one,
        observation=Observation(silhouette, obs.edge_distance[:, :, :1], obs.image[:, :, :1]),
        cameras=_first_camera(one.cameras),
        keypoint_joints=None,
    )
    plain = register(ref, one, settings=OTHER_BRANCHES)
    with UnplacedOnMeta(("motion", "pgm")):
        probed = register(ref, one, settings=OTHER_BRANCHES)
    assert probed.notes["unseen_frames"] == "2" and not probed.G_measured
    for field in ("C", "T_rotation", "T_translation", "A", "fit"):
        torch.testing.assert_close(getattr(plain, field), getattr(probed, field), rtol=0, atol=0)


def _first_camera(rig: CameraRig) -> CameraRig:
    return dataclasses.replace(
        rig, K=rig.K[:1], R=rig.R[:1], t=rig.t[:1], dist=rig.dist[:1], size=rig.size[:1],
        names=rig.names[:1],
    )  # fmt: skip


def test_the_probe_catches_a_tensor_made_off_the_device():
    """The probe itself: a factory call without a device, from the package's code, fails
    at its first use beside a CPU tensor; with a device, or from elsewhere, it does not."""
    from motion.smoothing import smooth_values

    values = torch.arange(10.0)
    with UnplacedOnMeta():
        torch.testing.assert_close(smooth_values(values, 1.0).sum(), values.sum())
        assert torch.zeros(2).device.type == "cpu"  # this test's own call: not probed
    with UnplacedOnMeta(("tests",)), pytest.raises((RuntimeError, NotImplementedError)):
        values + torch.zeros(10)  # made from a file under tests/: on meta


def test_a_device_this_machine_lacks_is_refused_by_name():
    with pytest.raises(RegistrationSettingsError, match="unknown device 'gpu'"):
        RegistrationSettings(device="gpu")
    with pytest.raises(RegistrationSettingsError, match="unsupported device 'meta'"):
        RegistrationSettings(device="meta")
    if not torch.cuda.is_available():
        with pytest.raises(RegistrationSettingsError, match=r"'cuda' asked for.*use device=cpu"):
            RegistrationSettings(device="cuda")
    else:
        count = torch.cuda.device_count()
        with pytest.raises(DeviceError, match=f"has {count} CUDA device"):
            resolve_device(f"cuda:{count}")
    assert resolve_device("cpu") == torch.device("cpu")


class _Pair(NamedTuple):
    x: torch.Tensor
    label: str


@dataclasses.dataclass(frozen=True)
class _Inner:
    values: torch.Tensor
    names: list[str]


@dataclasses.dataclass
class _Outer:
    inner: _Inner
    items: list
    pair: _Pair
    table: dict
    count: int = 3
    cache: torch.Tensor = dataclasses.field(init=False, default=None)

    def __post_init__(self):
        self.cache = self.inner.values * 2


def test_to_device_moves_every_tensor_at_any_depth_and_nothing_else():
    tree = _Outer(
        _Inner(torch.ones(2), ["a"]),
        [torch.zeros(1), (torch.ones(3), "b")],
        _Pair(torch.ones(1), "c"),
        {"k": torch.ones(4)},
    )
    moved = to_device(tree, "meta")
    tensors = [
        moved.inner.values,
        moved.items[0],
        moved.items[1][0],
        moved.pair.x,
        moved.table["k"],
        moved.cache,  # rebuilt by __post_init__ from the moved fields
    ]
    assert all(t.device.type == "meta" for t in tensors)
    assert isinstance(moved.pair, _Pair) and moved.pair.label == "c"
    assert moved.inner.names == ["a"] and moved.items[1][1] == "b" and moved.count == 3
    assert tree.inner.values.device.type == "cpu"  # the input is not changed
    same = to_device(tree, "cpu")
    assert same.inner.values is tree.inner.values  # already there: not copied


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_register_on_cuda_is_as_good_as_on_the_cpu(two_views):
    """The same input and settings on both devices (their random streams differ, so the
    results are two draws): the result comes back on the CPU, and it differs from the CPU's
    by no more than two CPU seeds' results differ. Measured on the CPU over seeds 0-5 (every
    pair): C's mean difference at most 1.1 frames, the mean fit IoU 0.011 apart, G 0.3 %
    apart; allowed here: 2 frames, 0.03 and 2 %."""
    _, ref, video = two_views
    results = {
        device: register(ref, video, settings=dataclasses.replace(BRANCHES, device=device))
        for device in ("cpu", "cuda")
    }
    cuda, cpu = results["cuda"], results["cpu"]
    assert all(x.device.type == "cpu" for x in (cuda.C, cuda.A, cuda.T_translation, cuda.fit))
    assert float((cuda.C - cpu.C).abs().float().mean()) <= 2.0, (cuda.C, cpu.C)
    assert bool((cuda.C[1:] >= cuda.C[:-1]).all())
    assert abs(float(cuda.fit.mean()) - float(cpu.fit.mean())) <= 0.03
    assert abs(cuda.G - cpu.G) <= 0.02 * cpu.G
