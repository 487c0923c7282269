"""The observation factor on a CUDA device (skipped where there is none, as in CI): the same
scores as on the CPU, every cue, occlusion on. Its CPU stand-in, the scores' stability under
rounding-level changes of the poses, is ``test_observation.py``'s
``test_every_cue_scores_the_same_under_rounding_of_the_poses``."""

import pytest
import torch

from tests.motion.body.conftest import every_cue_scene

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def test_every_cue_scores_the_same_on_cuda_as_on_the_cpu():
    x, rest, score = every_cue_scene()
    cpu, gpu = score(x, rest, "cpu"), score(x, rest, "cuda")
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=1e-9)
