"""Time-alignment throughput: ours beside dtaidistance and tslearn, measured in the same run.

Prints cells/s (T' x T cells per second, path included) of
  * our chain Viterbi (monotone steps 0..S, the registration path) -- motion.alignment.chain_align
  * our classic DTW (the proposal's Eq. 26)                        -- motion.alignment.dtw
  * dtaidistance warping_paths_fast + best_path (C; computes its own cost from two series)
  * tslearn dtw_path_from_metric(C, metric="precomputed")
on 1,000 x 5,000 and 2,000 x 10,000 cost matrices, then coarse-to-fine alignment of a
7,500-frame video against a 36,000-frame reference: wall time and the fraction of the
T' x T pairs it evaluates (what stage 1 of registration pays for), on smooth features and on
a periodic motion (a walk against a reference that repeats one 130-frame gait loop, issue
13), beside classic coarse-to-fine (one sample per coarse cell, no tracking: the algorithm
before issue 13) in the same run. On the loop, C is scored modulo the loop (a reference that
repeats one loop tells its copies apart only by the path).

Usage: python benchmarks/bench_alignment.py [--repeats N] [--skip-anchors] [--quick]
       [--json PATH]

``--quick``: 2 timed rounds instead of 5. ``--json PATH``: also write the figures as rows for
``benchmarks/report.py`` (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import math
import platform
import time

import numpy as np
import torch
from report import parse_args, write_rows  # benchmarks/report.py, beside this script

from motion.alignment import (
    chain_align,
    coarse_to_fine_align,
    dtw,
    sequence_cost_fn,
    slope_step_cost,
)
from motion.runtime import retain_freed_memory

#: ``--quick``: fewer timed rounds
QUICK = {"repeats": 2}
#: (ours, anchor) pairs of the throughput rows written with ``--json``
RATIOS = (("chain f32", "dtaidistance"), ("dtw", "dtaidistance"), ("chain f32", "tslearn"))


def best_times(fns: dict, repeats: int) -> dict[str, float]:
    """Best wall time of each function; rounds are interleaved so that every contender sees
    the same machine state (this machine's speed drifts by tens of percent over minutes)."""
    for fn in fns.values():
        fn()  # warm-up
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    return best


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark and prints its tables; returns its figures as rows (see
    ``benchmarks/report.py``), also written to ``--json`` when given."""
    retain_freed_memory()  # process-wide allocator setting (motion/runtime.py)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-anchors", action="store_true", help="skip dtaidistance/tslearn")
    parser.add_argument("--max-step", type=int, default=10)
    args = parse_args(parser, QUICK, argv)

    print(
        f"machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"threads {torch.get_num_threads()}"
    )
    rng = np.random.default_rng(0)
    rows = []
    for n, m in [(1000, 5000), (2000, 10000)]:
        x, y = rng.random(n), rng.random(m)
        cost64 = (x[:, None] - y[None]) ** 2
        cost32 = torch.from_numpy(cost64).float()
        cells = n * m
        cost64_t = torch.from_numpy(cost64)
        fns = {
            "chain f32": lambda c=cost32: chain_align(c, args.max_step),
            "chain f64": lambda c=cost64_t: chain_align(c, args.max_step),
            "dtw": lambda c=cost64_t: dtw(c),
        }
        if not args.skip_anchors:
            from dtaidistance import dtw as dtai
            from tslearn.metrics import dtw_path_from_metric

            def dtai_path(x=x, y=y):
                _, paths = dtai.warping_paths_fast(x, y)
                return dtai.best_path(paths)

            fns["dtaidistance"] = dtai_path
            fns["tslearn"] = lambda c=cost64: dtw_path_from_metric(c, metric="precomputed")
        entry = {"size": f"{n} x {m}"}
        entry.update({k: cells / v for k, v in best_times(fns, args.repeats).items()})
        rows.append(entry)

    cols = list(rows[0].keys())
    print("\nthroughput with path, Mcells/s (higher is better)")
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join([r["size"]] + [f"{r[c] / 1e6:.0f}" for c in cols[1:]]) + " |")
    if not args.skip_anchors:
        for r in rows:
            print(
                f"{r['size']}: chain f32 / dtaidistance = {r['chain f32'] / r['dtaidistance']:.2f}x, "
                f"dtw / dtaidistance = {r['dtw'] / r['dtaidistance']:.2f}x, "
                f"chain f32 / tslearn = {r['chain f32'] / r['tslearn']:.2f}x"
            )
    pairs = RATIOS if not args.skip_anchors else [(k, None) for k in cols[1:]]
    results = [
        dict(
            case=f"{r['size']}, with path",
            ours=ours,
            value=r[ours] / 1e6,
            anchor=anchor,
            anchor_value=r[anchor] / 1e6 if anchor else None,
            units="Mcells/s",
            better="higher",
        )
        for r in rows
        for ours, anchor in pairs
    ]

    # Coarse-to-fine: 7,500 video frames (25 fps, 5 min) against 36,000 reference frames
    # (120 Hz, 5 min), 16-D features, a smooth non-linear warp of average slope 4.8.
    g = torch.Generator().manual_seed(0)
    num_ref, num_video = 36_000, 7_500
    t = torch.arange(num_ref, dtype=torch.float32)
    freqs = torch.rand(16, generator=g) * 0.01 + 0.002
    ref = torch.sin(t[:, None] * freqs + torch.rand(16, generator=g) * 2 * math.pi)
    u = torch.linspace(0, 1, num_video)
    true = ((u + 0.03 * torch.sin(6 * math.pi * u)) * (num_ref - 1)).round().long()
    video = ref[true] + 0.02 * torch.randn(num_video, 16, generator=g)
    print(f"\ncoarse-to-fine 7,500 x 36,000 (S={args.max_step}), target < 2 s")
    print("| features | method | seconds | pairs evaluated | mean abs(C - C_true) | in phase |")
    print("|---|---|---|---|---|---|")
    results += c2f_rows(sequence_cost_fn(video, ref), num_ref, true, None, {}, args)
    # A walk against a reference repeating one gait loop of 130 frames (1.1 s at 120 Hz):
    # phase sine/cosine and harmonics; the student walks at 96 % of the reference's pace,
    # +-10 % over the 5 minutes; robust cost and a slope prior around the frame-rate ratio
    # 4.8, as stage 1 of registration sets them.
    period = 130.0
    phase = 2 * math.pi * torch.arange(num_ref, dtype=torch.float32) / period
    loop = torch.stack(
        [phase.sin(), phase.cos(), 0.5 * (2 * phase).sin(), 0.5 * (2 * phase).cos()], 1
    )
    rate = 4.6 * (1 + 0.1 * torch.sin(2 * math.pi * 1.3 * u + 1.0))
    walk = (20 + torch.cumsum(rate, 0) - rate[0]).round().long().clamp(max=num_ref - 1)
    student = loop[walk] + 0.05 * torch.randn(num_video, 4, generator=g)
    stage1 = {
        "radius": args.max_step + 4,
        "max_cells": 2000,
        "robust": "truncate",
        "step_cost": slope_step_cost(args.max_step, 4.8, 0.02).double(),
    }
    results += c2f_rows(sequence_cost_fn(student, loop), num_ref, walk, period, stage1, args)
    return write_rows(args.json, results)


def c2f_rows(fn, num_ref: int, true, period, settings: dict, args) -> list[dict]:
    """Table rows for classic and current coarse-to-fine on one problem (C_true ``true``;
    ``period`` scores C modulo a loop of that many reference frames), printed; returns
    them as report rows, current against classic."""
    num_video = len(true)
    methods = {
        "classic (before issue 13)": {"pool_stride": num_ref, "beam": 0},
        "min-pooled + tracking": {},
    }
    figures = {}
    for name, extra in methods.items():
        counted = []

        def count(rows, cols, counted=counted):
            counted.append(cols.numel())
            return fn(rows, cols)

        kwargs = {**settings, **extra}
        seconds = best_times(
            {
                name: lambda kw=kwargs: coarse_to_fine_align(
                    fn, num_video, num_ref, args.max_step, **kw
                )
            },
            args.repeats,
        )[name]
        path = coarse_to_fine_align(count, num_video, num_ref, args.max_step, **kwargs).path[0]
        err = (path - true).abs().float()
        phase = "-"
        figures[name] = {
            "seconds": (seconds, "s", "lower"),
            "pairs evaluated": (100 * sum(counted) / (num_video * num_ref), "% of T' x T", "lower"),
            "mean abs(C - C_true)": (err.mean().item(), "frames", "lower"),
        }
        if period is not None:
            off = err.remainder(period)
            in_phase = (torch.minimum(off, period - off) <= 5).float().mean().item()
            phase = f"{in_phase:.1%} within 5"
            figures[name]["in phase (within 5)"] = (100 * in_phase, "%", "higher")
        print(
            f"| {'loop' if period else 'smooth'} | {name} | {seconds:.2f} | "
            f"{sum(counted) / (num_video * num_ref):.3%} | {err.mean().item():.1f} | {phase} |"
        )
    (ours, mine), (anchor, theirs) = reversed(figures.items())
    case = f"coarse-to-fine {num_video:,} x {num_ref:,}, {'loop' if period else 'smooth'}"
    return [
        dict(
            case=f"{case}: {what}",
            ours=ours,
            value=value,
            anchor=anchor,
            anchor_value=theirs[what][0],
            units=units,
            better=better,
        )
        for what, (value, units, better) in mine.items()
    ]


if __name__ == "__main__":
    main()
