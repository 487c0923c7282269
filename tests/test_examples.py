"""The examples run and do what they claim (pgm reused for another articulated object)."""

import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_planar_arm_is_posed_from_a_perturbed_start():
    arm = _load("planar_arm")
    assert "motion" not in arm.__dict__  # pgm only
    errors = arm.run(num_particles=120, batch=4, seed=1, verbose=False)
    assert errors["start"] > 0.05  # 30 degree perturbations: several centimetres off
    assert errors["final"] < 0.25 * errors["start"]
    assert errors["final"] < 0.03  # within 3 cm with 1 cm observation noise


def test_planar_arm_factor_densities_are_consistent():
    """LinkJoint's samplers draw from its own normalised density: check the sample moments."""
    import torch

    arm = _load("planar_arm")
    factor = arm.LinkJoint(arm.LENGTHS[:1], pos_std=0.02, angle_std=0.1)
    src = torch.tensor([[[[0.1, -0.2, 0.7]]]], dtype=torch.float64).expand(1, 1, 100_000, 3)
    g = torch.Generator().manual_seed(0)
    fwd = factor.sample_target(src, slice(None), True, g)
    end = arm.link_end(src[0, 0, 0], arm.LENGTHS[0])
    torch.testing.assert_close(fwd[0, 0, :, :2].mean(0), end, atol=1e-3, rtol=0)
    torch.testing.assert_close(
        fwd[0, 0, :, 2].std(), torch.tensor(0.1, dtype=torch.float64), rtol=0.02, atol=0
    )
    # the density integrates to 1 along theta at the mode position (1-D numerical check)
    th = torch.linspace(0.7 - 1.0, 0.7 + 1.0, 4001, dtype=torch.float64)
    tgt = torch.stack([end[0].expand(4001), end[1].expand(4001), th], -1)[None, None]
    dens = factor.log_target_density(tgt, src[:, :, :1], slice(None), True)[0, 0, :, 0].exp()
    mass_theta = torch.trapezoid(dens, th) * (
        2 * torch.pi * 0.02**2
    )  # times the 2-D position normaliser
    assert abs(mass_theta.item() - 1.0) < 1e-3


def test_render_walk_writes_the_readme_picture(tmp_path):
    out = _load("render_walk").main(tmp_path / "walk.png")
    assert out.stat().st_size > 10_000


def test_render_walk_leaves_the_tracked_picture_alone_by_default():
    module = _load("render_walk")
    assert module._out_path([]) == module.DEFAULT_OUT
    assert module.DEFAULT_OUT.parts[0] == "runs"
    assert module._out_path(["--docs"]) == module.DOCS_OUT
    assert module._out_path(["x.png"]) == Path("x.png")
