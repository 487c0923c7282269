"""Command line.

``python -m experiments demo [--bvh FILE] [--seed N] [--out-dir DIR]``: the time-alignment demo.
``python -m experiments run CONFIG.yaml [key=value ...]``: run a config (``seed=``,
``out_dir=`` and ``tiny=true`` are always accepted); exits non-zero with a one-line reason.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiments.config import ConfigError, ExperimentSkipped, parse_overrides
from experiments.demo import BUNDLED_BVH, run_demo
from experiments.runtime import retain_freed_memory


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo", help="time-align a bundled motion against a warped, corrupted copy"
    )
    demo.add_argument("--bvh", type=Path, default=BUNDLED_BVH, help="reference BVH file")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--out-dir", type=Path, default=Path("runs/demo"))
    run = sub.add_parser("run", help="run a YAML config (see experiments/README.md)")
    run.add_argument("config", type=Path)
    run.add_argument("overrides", nargs="*", help="key=value settings")
    args = parser.parse_args(argv)
    retain_freed_memory()  # a process-wide allocator setting: see experiments/runtime.py

    if args.command == "run":
        from experiments.runner import run_config

        try:
            metrics = run_config(args.config, parse_overrides(args.overrides))
        except ExperimentSkipped as why:
            print(f"skipped: {why}")
            return 0
        except (ConfigError, OSError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
        width = max(len(k) for k in metrics)
        for key, value in sorted(metrics.items()):
            print(f"{key:<{width}}  {value:.4g}")
        return 0

    if args.command == "demo":
        if not args.bvh.is_file():
            parser.error(f"--bvh: no such file: {args.bvh}")
        m = run_demo(args.bvh, args.out_dir, args.seed)
        print(
            f"reference {args.bvh.name}: {m['num_ref']} frames at 120 Hz; "
            f"input {m['num_video']} frames at 25 fps, a stretch replaced by later frames"
        )
        print("mean |C - C_true| in reference frames (lower is better)")
        print(f"{'method':<22}{'all':>8}{'outside':>10}{'inside':>9}{'seconds':>10}")
        for key, label in [
            ("dtw", "proposal DTW (Eq. 26)"),
            ("chain", "chain Viterbi"),
            ("robust", "robust chain"),
        ]:
            print(
                f"{label:<22}{m[f'c_err_mean_{key}']:>8.2f}{m[f'c_err_outside_mean_{key}']:>10.2f}"
                f"{m[f'c_err_inside_mean_{key}']:>9.2f}{m[f'seconds_{key}']:>10.4f}"
            )
        print(f"wrote {args.out_dir / 'metrics.json'} and {args.out_dir / 'alignment.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
