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
from motion.registration import RegistrationSettings, pipeline, register
from motion.registration.approximate import Stage1Settings
from motion.registration.inputs import features_from_sequence
from motion.registration.pipeline import RegistrationSettingsError
from motion.registration.polish import PosturePolishSettings
from motion.registration.refine import RefineSettings
from motion.registration.types import Reference
from motion.synth import SynthConfig, synthesize
from tests.device_probe import (
    META,
    EmulatedDevice,
    Mixed,
    OnDevice,
    UnplacedOnMeta,
    emulated_to_device,
)
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


@pytest.fixture(scope="module")
def one_view(two_views):
    """The same student seen by its first camera alone, without 2-D joints, frames 4-5
    unseen."""
    _, ref, video = two_views
    obs = video.observation
    silhouette = obs.silhouette[:, :, :1].clone()
    silhouette[:, 4:6] = 0.0  # unseen
    one = dataclasses.replace(
        video,
        observation=Observation(silhouette, obs.edge_distance[:, :, :1], obs.image[:, :, :1]),
        cameras=_first_camera(video.cameras),
        keypoint_joints=None,
    )
    return ref, one


def test_the_other_branches_follow_the_inputs_device_too(one_view):
    ref, one = one_view
    plain = register(ref, one, settings=OTHER_BRANCHES)
    with UnplacedOnMeta(("motion", "pgm")):
        probed = register(ref, one, settings=OTHER_BRANCHES)
    assert probed.notes["unseen_frames"] == "2" and not probed.G_measured
    for field in ("C", "T_rotation", "T_translation", "A", "fit"):
        torch.testing.assert_close(getattr(plain, field), getattr(probed, field), rtol=0, atol=0)


@pytest.mark.parametrize("case", ["branches", "other branches"])
def test_host_tensors_meet_the_devices_only_where_a_gpu_takes_them(
    case, two_views, one_view, monkeypatch
):
    """On a second device emulated on the CPU (:class:`tests.device_probe.EmulatedDevice`:
    the inputs stand for a GPU's tensors, what the code makes on the CPU -- the time
    alignments, graph structure, NumPy -- for the host's, and an operation mixing the two
    fails where a GPU would refuse it) the whole ``register()`` runs, through the code paths
    meant for a GPU, and its result is as good as the plain run's.
    This sees what :class:`UnplacedOnMeta` cannot: host tensors made on purpose that reach
    the device's computations without being moved."""
    if case == "branches":
        (_, ref, video), settings = two_views, BRANCHES
    else:
        (ref, video), settings = one_view, OTHER_BRANCHES
    plain = register(ref, video, settings=settings)
    monkeypatch.setattr(pipeline, "resolve_device", lambda name: META)
    monkeypatch.setattr(pipeline, "to_device", emulated_to_device)
    with EmulatedDevice():
        emulated = register(ref, video, settings=settings)
    assert type(emulated.C) is torch.Tensor  # handed back to the host
    # the code paths meant for a GPU (pgm's chunking, the generic chain Viterbi where the
    # CPU's is NumPy's) may break ties and sum in another order: a GPU's result, not the CPU's
    _as_good_as(emulated, plain)


def test_the_emulated_device_refuses_what_a_gpu_refuses():
    """The emulation itself: a device tensor beside a host one fails (but not a host index
    or a host scalar), a tensor made with the device tensor's device is the device's, and
    ``.cpu()`` / ``device="cpu"`` give the host's."""
    with EmulatedDevice():
        x = torch.arange(6.0).as_subclass(OnDevice)
        host = torch.ones(6)
        with pytest.raises(Mixed, match="host tensor of shape \\(6,\\)"):
            x + host
        assert type(x + torch.tensor(1.0)) is OnDevice  # a 0-dim host scalar is taken
        assert type(x[torch.tensor([0, 2])]) is OnDevice  # so is a host index
        made = torch.zeros(6, device=x.device)
        assert type(made) is OnDevice and type(x + made) is OnDevice
        assert type(host.to(x.device)) is OnDevice and type(x.cpu()) is torch.Tensor
        assert type(torch.as_tensor(x, device="cpu")) is torch.Tensor
        with pytest.raises(Mixed, match="numpy"):
            x.numpy()
    assert torch.Generator is not None and torch.zeros(1).device.type == "cpu"


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
    _as_good_as(cuda, cpu)


def _as_good_as(result, cpu):
    """``result`` (another device's) differs from the CPU's ``cpu`` by no more than two CPU
    seeds' results differ (see the CUDA test's docstring for the measured spread)."""
    assert float((result.C - cpu.C).abs().float().mean()) <= 2.0, (result.C, cpu.C)
    assert bool((result.C[1:] >= result.C[:-1]).all())
    assert abs(float(result.fit.mean()) - float(cpu.fit.mean())) <= 0.03
    assert abs(result.G - cpu.G) <= 0.02 * cpu.G
