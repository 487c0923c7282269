"""Particle BP throughput: a 15-part body tree of SE(3) nodes, K = 150, 80 frames, 6 iterations.

Prints seconds per iteration of `pgm.particle_bp` (all 80 frames batched) beside a
straightforward implementation of the same algorithm written here with Python loops over
frames, nodes and edges (particles stay tensors), measured in the same run. The unary is a
cheap synthetic Gaussian around a known pose; its cost is included in both (it is small).

Usage: python benchmarks/bench_particle_bp.py [--frames 80] [--particles 150] [--loop-frames 4]
       [--repeats 3] [--device cpu|cuda] [--quick] [--json PATH]

With ``--device cuda`` the same problem (drawn on the CPU) is solved on the GPU; the loop
version always runs on the CPU (``--loop-frames 0`` skips it). ``--quick``: 20 frames, 3
iterations, one round, the loop version on 2 frames. ``--json PATH``: also write the figures
as rows for ``benchmarks/report.py`` (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import math
import time

import torch
from report import parse_args, write_rows  # benchmarks/report.py, beside this script

from motion.runtime import retain_freed_memory
from pgm.continuous import RigidConnection, UnaryFactor
from pgm.particle_bp import ParticleGraph, particle_bp
from pgm.rotations import qexp, qmul, qrotate
from pgm.semiring import LogSemiring
from pgm.spaces import SE3

#: ``--quick``: a smaller problem, one round
QUICK = {"frames": 20, "iterations": 3, "repeats": 1, "loop_frames": 2}

# pelvis 0; torso 1, head 2; arms 3-5 / 6-8; legs 9-11 / 12-14 (parent, child)
EDGES = torch.tensor(
    [
        [0, 1],
        [1, 2],
        [1, 3],
        [3, 4],
        [4, 5],
        [1, 6],
        [6, 7],
        [7, 8],
        [0, 9],
        [9, 10],
        [10, 11],
        [0, 12],
        [12, 13],
        [13, 14],
    ]
)


class PoseUnary(UnaryFactor):
    """Cheap synthetic observation: Gaussian on each part's position around the truth."""

    def __init__(self, truth, std):
        self.truth, self.std = truth, std

    def log_potential(self, x, nodes, estimates):
        d2 = (x[..., :3] - self.truth[:, nodes, None, :3]).square().sum(-1)
        return -0.5 * d2 / self.std**2


def make_problem(frames: int, k: int, seed: int = 0, device: str = "cpu"):
    g = torch.Generator().manual_seed(seed)
    v = 15
    offsets = torch.randn(len(EDGES), 3, generator=g) * 0.1
    factor = RigidConnection(offsets, torch.zeros(len(EDGES), 3), pos_std=0.02, rot_std=0.3)
    # A pose consistent with the connections: child rotation near its parent's, child
    # position at the parent's joint (offset_b = 0).
    truth = torch.zeros(frames, v, 7)
    truth[:, 0, 3:] = qexp(torch.randn(frames, 3, generator=g) * 0.5)
    for e, (a, c) in enumerate(EDGES.tolist()):  # edges are in topological order
        truth[:, c, 3:] = qmul(truth[:, a, 3:], qexp(torch.randn(frames, 3, generator=g) * 0.2))
        truth[:, c, :3] = truth[:, a, :3] + qrotate(truth[:, a, 3:], offsets[e].expand(frames, 3))
    graph = ParticleGraph(
        v,
        [(SE3(), torch.arange(v))],
        [(EDGES, factor)],
        [(torch.arange(v), PoseUnary(truth, 0.05))],
    )
    initial = SE3().perturb(truth.unsqueeze(2).expand(frames, v, k, 7), (0.05, 0.2), g)
    if device != "cpu":  # the same problem (drawn on the CPU), solved on another device
        graph.unary[0][1].truth = truth = truth.to(device)
        initial = initial.to(device)
    return graph, initial, factor, truth


def loop_iteration(values, log_w, factor, unary, generator, kernel=(0.01, 0.05)):
    """One iteration of the same algorithm, straightforwardly: loops over frames, nodes, edges."""
    space = SE3()
    b, v, k, _ = values.shape
    edges = EDGES.tolist()
    nbrs = {j: [] for j in range(v)}
    for e, (a, c) in enumerate(edges):
        nbrs[c].append((e, a, True))
        nbrs[a].append((e, c, False))
    new_values = torch.empty_like(values)
    new_logw = torch.empty_like(log_w)
    for f in range(b):
        # proposal: half own marginal, half the neighbours pushed through psi
        log_q = torch.empty(v, k)
        for j in range(v):
            comps = [None, *nbrs[j]]
            w = torch.full((len(comps),), 0.5 / max(1, len(comps) - 1))
            w[0] = 0.5 if len(comps) > 1 else 1.0
            choice = torch.multinomial(w, k, replacement=True, generator=generator)
            samples = torch.empty(k, 7)
            for c_idx, comp in enumerate(comps):
                sel = (choice == c_idx).nonzero().flatten()
                if len(sel) == 0:
                    continue
                src = j if comp is None else comp[1]
                idx = torch.multinomial(
                    log_w[f, src].exp(), len(sel), replacement=True, generator=generator
                )
                x = values[f, src, idx]
                if comp is None:
                    samples[sel] = space.perturb(x, kernel, generator)
                else:
                    e, _, fwd = comp
                    samples[sel] = factor.sample_target(
                        x[None, None], torch.tensor([e]), fwd, generator
                    )[0, 0]
            dens = []
            for comp in comps:
                if comp is None:
                    lk = space.log_kernel(samples, values[f, j], kernel)
                    dens.append(torch.logsumexp(lk + log_w[f, j], -1))
                else:
                    e, i, fwd = comp
                    lk = factor.log_target_density(
                        samples[None, None], values[f, i][None, None], torch.tensor([e]), fwd
                    )[0, 0]
                    dens.append(torch.logsumexp(lk + log_w[f, i], -1))
            log_q[j] = torch.logsumexp(torch.stack(dens) + torch.log(w)[:, None], 0)
            new_values[f, j] = samples
        # weighting: unary, tables, two-pass messages on the tree, marginals
        phi = unary.log_potential(new_values[f : f + 1], torch.arange(v), None)[0] - log_q
        tables = {}
        for e, (a, c) in enumerate(edges):
            tables[e] = factor.log_potential(
                torch.tensor([e]), new_values[f, a][None, None], new_values[f, c][None, None], k
            )[0, 0]
        up, down = {}, {}
        for e in reversed(range(len(edges))):  # children before parents (edges are topological)
            a, c = edges[e]
            h = phi[c].clone()
            for e2, (a2, _) in enumerate(edges):
                if a2 == c:
                    h = h + up[e2]
            up[e] = torch.logsumexp(tables[e] + h[None, :], 1)
        for e in range(len(edges)):
            a, c = edges[e]
            h = phi[a].clone()
            for e2, (a2, c2) in enumerate(edges):
                if a2 == a and e2 != e:
                    h = h + up[e2]
                if c2 == a:
                    h = h + down[e2]
            down[e] = torch.logsumexp(tables[e] + h[:, None], 0)
        for j in range(v):
            belief = phi[j].clone()
            for e, (a, c) in enumerate(edges):
                if a == j:
                    belief = belief + up[e]
                if c == j:
                    belief = belief + down[e]
            new_logw[f, j] = torch.log_softmax(belief, -1)
    return new_values, new_logw


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark and prints its table; returns its figures as rows (see
    ``benchmarks/report.py``), also written to ``--json`` when given."""
    retain_freed_memory()  # process-wide allocator setting (motion/runtime.py)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=80)
    parser.add_argument("--particles", type=int, default=150)
    parser.add_argument("--iterations", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3, help="interleaved rounds; best of each")
    parser.add_argument(
        "--loop-frames",
        type=int,
        default=4,
        help="frames run through the loop version (its time is scaled to --frames); 0: skip it",
    )
    parser.add_argument("--device", default="cpu", help="where pgm.particle_bp runs (cpu, cuda)")
    args = parse_args(parser, QUICK, argv)
    torch.manual_seed(0)
    device = args.device
    graph, initial, factor, truth = make_problem(args.frames, args.particles, device=device)
    g = torch.Generator(device=device).manual_seed(1)
    warm, warm_initial, _, _ = make_problem(2, args.particles, device=device)
    particle_bp(warm, warm_initial, iterations=2, generator=g, kernel_scale=(0.01, 0.05))
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    if args.loop_frames:  # the loop version runs on the CPU
        _, small, _, small_truth = make_problem(args.frames, args.particles)
        small = small[: args.loop_frames]
        sub_unary = PoseUnary(small_truth[: args.loop_frames], 0.05)
        g_loop = torch.Generator().manual_seed(2)
    # Interleaved rounds, best of each: this machine's speed drifts by tens of percent
    # between seconds, and the minimum is the least disturbed measurement.
    ours, errs, loops = {None: [], 30: []}, {}, []
    for _ in range(args.repeats):
        for centres in (None, 30):
            sync()
            t0 = time.perf_counter()
            res = particle_bp(
                graph,
                initial,
                iterations=args.iterations,
                generator=g,
                kernel_scale=(0.01, 0.05),
                semiring=LogSemiring(),
                proposal_centres=centres,
            )
            sync()
            ours[centres].append((time.perf_counter() - t0) / args.iterations)
            errs[centres] = SE3.position_distance(res.mean, truth).mean().item()
        if not args.loop_frames:
            continue
        log_w = torch.full(small.shape[:3], -math.log(args.particles))
        values = small
        t0 = time.perf_counter()
        for _ in range(2):
            values, log_w = loop_iteration(values, log_w, factor, sub_unary, g_loop)
        loops.append((time.perf_counter() - t0) / 2 * args.frames / args.loop_frames)
    ours = {c: min(t) for c, t in ours.items()}
    loop = min(loops) if loops else math.nan
    where = torch.cuda.get_device_name() if device.startswith("cuda") else f"{device}"
    print(
        f"15-node SE(3) tree, K={args.particles}, {args.frames} frames (torch {torch.__version__}, "
        f"{torch.get_num_threads()} CPU threads, particle_bp on {where})"
    )
    print(
        "| implementation | s / iteration (all frames) | speed-up vs loops | mean position error |"
    )
    print("|---|---|---|---|")
    print(
        f"| Python loops over frames, nodes, edges | {loop:.2f} (measured on {args.loop_frames} frames, scaled) | 1x | |"
    )
    for centres, label in ((None, "all K"), (30, "30 resampled")):
        print(
            f"| pgm.particle_bp, proposal centres: {label} | {ours[centres]:.3f} | "
            f"{loop / ours[centres]:.1f}x | {errs[centres] * 100:.1f} cm |"
        )
    print("targets: >= 20x the loop version, < 0.25 s / iteration")
    case = f"15-node SE(3) tree, K={args.particles}, {args.frames} frames, on {where}"
    loop_name = f"Python loops over frames, nodes, edges (on {args.loop_frames} frames, scaled)"
    results = []
    for centres, label in ((None, "all K"), (30, "30 resampled")):
        ours_name = f"pgm.particle_bp, proposal centres: {label}"
        results += [
            dict(
                case=f"{case}: seconds per iteration",
                ours=ours_name,
                value=ours[centres],
                anchor=loop_name if loops else None,
                anchor_value=loop if loops else None,
                units="s / iteration",
                better="lower",
            ),
            dict(
                case=f"{case}: mean position error",
                ours=ours_name,
                value=errs[centres] * 100,
                anchor=None,
                anchor_value=None,
                units="cm",
                better="lower",
            ),
        ]
    return write_rows(args.json, results)


if __name__ == "__main__":
    main()
