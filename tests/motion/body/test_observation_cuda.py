"""The observation factor on a CUDA device (skipped where there is none, as in CI): the same
scores as on the CPU, every cue, occlusion on."""

import pytest
import torch

from motion.body.observation import (
    BodyObservation,
    Edges,
    Intensity,
    Joints2D,
    NonPenetration,
    Observation,
    PartShapes,
    Silhouette,
    poses_from_segments,
)
from motion.render import project_parts, silhouette
from pgm import SE3
from tests.motion.body.conftest import F64, side_camera, walk_segments

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def test_every_cue_scores_the_same_on_cuda_as_on_the_cpu():
    seg, model = walk_segments([30, 60])
    poses = poses_from_segments(seg)  # (2, P, 7)
    shapes = PartShapes.from_segments(seg[0], model.radii)
    rig = side_camera()
    sil = torch.stack(
        [silhouette(project_parts(rig, s, model.radii), 120, 160)[0] for s in seg]
    ).to(F64)
    g = torch.Generator().manual_seed(0)
    image = torch.rand(1, 2, 1, 3, 120, 160, generator=g, dtype=F64)
    dist = 10 * torch.rand(1, 2, 1, 120, 160, generator=g, dtype=F64)
    keypoints = torch.cat(
        [
            100 * torch.rand(1, 2, 1, 30, 2, generator=g, dtype=F64),
            torch.ones(1, 2, 1, 30, 1, dtype=F64),
        ],
        -1,
    )
    x = SE3().perturb(poses.reshape(1, 30, 1, 7).expand(1, 30, 40, 7), (0.03, 0.3), g)

    def cues(device):
        return [
            Silhouette(),
            Edges(),
            Intensity(
                torch.rand(15, 3, generator=torch.Generator().manual_seed(1), dtype=F64).to(device)
            ),
            Joints2D(torch.arange(30).reshape(15, 2).to(device)),
            NonPenetration(torch.eye(15, dtype=torch.bool, device=device)),
        ]

    def score(device):
        obs = Observation(
            sil[None, :, None].to(device), dist.to(device), image.to(device), keypoints.to(device)
        )
        f = BodyObservation(
            PartShapes(shapes.axis.to(device), shapes.radii.to(device)),
            rig.to(device),
            obs,
            cues(device),
        )
        nodes = torch.arange(30, device=device)
        return f.log_potential(x.to(device), nodes, poses.reshape(1, 30, 7).to(device))

    cpu, gpu = score("cpu"), score("cuda")
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=1e-9)
