"""Command line of the experiments.

  python -m experiments run CONFIG.yaml [key=value ...] [--backend ray [--address ADDRESS]]
                                 [--cpus-per-task N] [--force]
      run a config (seed=, out_dir= and tiny=true are always accepted; values are YAML,
      e.g. methods=[dtw,robust]); results go to out_dir (metrics.json, timings.json, ...).
      --backend sequential (default): the runs one after another in this process;
      --backend ray: each sweep entry a Ray task (pip install .[distributed]) on a local Ray
      started for the command, or with --address auto / ray://HOST:PORT on that cluster;
      --cpus-per-task: CPUs (= torch threads) per Ray task, default 1. A run whose folder
      holds a record of the same resolved config is not rerun; --force reruns it. Runs that
      fail are reported by label, the others finish, and the command exits with status 1.
  python -m experiments summarise OUT_DIR [--metrics a,b] [--over seed,warp_seed] [--title T]
                                 [--to FILE]
      a results page (Markdown) from the run records in OUT_DIR: provenance (commit, date,
      machine, threads), then a row per group of runs that differ only in their seeds,
      each metric as mean +- std; printed, or written to FILE (e.g. docs/results/X.md)
  python -m experiments list
      the experiments, their config files and every field (type, range, default, meaning)
  python -m experiments demo [--bvh FILE] [--seed N] [--out-dir DIR]
      the time-alignment demo on a bundled motion

Bad input (a config mistake, an unknown key, a value out of range, a missing file) prints
one line, "error: ...", to stderr and exits with status 2; --debug shows the traceback too.
A sweep whose runs partly fail prints one line naming them and exits with status 1 (--debug:
each failed run's traceback first).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import textwrap
from pathlib import Path

from experiments.backends import BACKENDS, make_backend
from experiments.config import ExperimentSkipped, parse_overrides
from experiments.demo import BUNDLED_BVH, run_demo
from experiments.summarise import SEED_KEYS, SummariseError, load_runs, results_markdown
from motion.cli import Parser, UsageError, add_debug, one_line, run
from motion.runtime import retain_freed_memory
from motion.settings import describe

__all__ = ["EXIT_RUNS_FAILED", "experiments_help", "main"]

#: exit status of a run command some of whose runs failed (bad input is 2)
EXIT_RUNS_FAILED = 1


def _registry():
    from experiments.runner import CONFIGS, EXPERIMENTS

    return CONFIGS, EXPERIMENTS


def _configs_of(name: str) -> list[str]:
    configs, _ = _registry()
    return [
        f"experiments/configs/{p.name}"
        for p in sorted(configs.glob("*.yaml"))
        if f"experiment: {name}" in p.read_text()
    ]


def experiments_help(details: bool = False) -> str:
    """The experiments and their fields: names only, or (``details``) each field's default,
    type, range and meaning."""
    _, experiments = _registry()
    lines = ["experiments (python -m experiments list: every field's type, range and meaning):"]
    for name, exp in experiments.items():
        configs = ", ".join(_configs_of(name)) or "no shipped config"
        lines.append(f"{name} ({configs}; schema {exp.schema.__name__}):")
        if details:
            # tiny, declared once on ExperimentConfig, means what each schema says it does
            meanings = {"tiny": exp.schema.TINY_DOC} if exp.schema.TINY_DOC else None
            lines += describe(exp.schema, text_syntax=False, meanings=meanings)
            if exp.schema.TINY:
                tiny = ", ".join(f"{k}={v}" for k, v in exp.schema.TINY.items())
                lines.append(f"  tiny=true sets: {tiny} (command-line values win)")
        else:
            fields = ", ".join(f.name for f in dataclasses.fields(exp.schema))
            lines += textwrap.wrap(fields, 96, initial_indent="  ", subsequent_indent="  ")
    return "\n".join(lines)


def _int_at_least(minimum: int):
    """An argparse type: an integer >= ``minimum``, else a message with what was given."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected an integer >= {minimum}; got {text!r}"
            ) from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}; got {value}")
        return value

    return parse


def _parser() -> Parser:
    parser = Parser(prog="python -m experiments", description=__doc__, epilog=experiments_help())
    add_debug(parser)
    sub = parser.add_subparsers(dest="command", required=True, metavar="{run,summarise,list,demo}")
    run_p = sub.add_parser(
        "run",
        help="run a YAML config (see experiments/README.md)",
        description="Run a YAML config with key=value overrides (YAML values). A run whose "
        "folder already holds a record of the same resolved config is not rerun (--force "
        "reruns it); runs that fail are named on one error line and the status is 1.",
        epilog=experiments_help(),
    )
    add_debug(run_p, top=False)
    run_p.add_argument("config", type=Path, help="a config file, e.g. experiments/configs/...")
    run_p.add_argument(
        "overrides", nargs="*", default=[], help="key=value settings (fields of the schema)"
    )
    run_p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="sequential",
        help="where the runs execute: one after another in this process (default), or one "
        "Ray task per sweep entry (needs pip install .[distributed])",
    )
    run_p.add_argument(
        "--address",
        default=None,
        metavar="ADDRESS",
        help="with --backend ray: the cluster to join (auto, or ray://HOST:PORT); "
        "omitted: start a local Ray on this machine for the command",
    )
    run_p.add_argument(
        "--cpus-per-task",
        type=_int_at_least(1),
        default=None,
        metavar="N",
        help="with --backend ray: CPUs each task asks for and torch threads it uses (default 1)",
    )
    run_p.add_argument(
        "--force",
        action="store_true",
        help="rerun runs whose folder already holds a record of the same resolved config",
    )
    summ = sub.add_parser(
        "summarise",
        help="a results page (Markdown, mean +- std over seeds) from a sweep's run records",
        description="Read the run records in OUT_DIR (one run, or a sweep's folder) and write "
        "a Markdown page: their provenance and a row per group of runs that differ only in "
        "the --over keys, each metric as mean +- std over the group.",
    )
    add_debug(summ, top=False)
    summ.add_argument("out_dir", type=Path, help="the runs' out_dir (e.g. runs/register_cross)")
    summ.add_argument(
        "--metrics", default=None, help="comma-separated metric names (default: all, in order)"
    )
    summ.add_argument(
        "--over",
        default=",".join(SEED_KEYS),
        help="comma-separated config keys whose runs are repetitions (default: seed,warp_seed)",
    )
    summ.add_argument("--title", default=None, help="the page's title (default: OUT_DIR's name)")
    summ.add_argument("--to", type=Path, default=None, help="write the page here (default: print)")
    list_p = sub.add_parser("list", help="list the experiments and their fields")
    add_debug(list_p, top=False)
    demo = sub.add_parser(
        "demo", help="time-align a bundled motion against a warped, corrupted copy"
    )
    add_debug(demo, top=False)
    demo.add_argument("--bvh", type=Path, default=BUNDLED_BVH, help="reference BVH file")
    demo.add_argument("--seed", type=_int_at_least(0), default=0, help="seed (an integer >= 0)")
    demo.add_argument("--out-dir", type=Path, default=Path("runs/demo"), help="output folder")
    return parser


def _print_metrics(metrics: dict) -> None:
    width = max((len(k) for k in metrics), default=0)
    for key, value in sorted(metrics.items()):
        print(f"{key:<{width}}  {value:.4g}")


def _run(args: argparse.Namespace) -> int:
    from experiments.runner import SweepFailed, run_config

    if args.backend != "ray":
        for flag, value in (("--address", args.address), ("--cpus-per-task", args.cpus_per_task)):
            if value is not None:
                raise UsageError(f"{flag}: only with --backend ray; got --backend {args.backend}")
    overrides = parse_overrides(args.overrides)
    backend = make_backend(args.backend, args.address)  # says how to install Ray if missing
    try:
        metrics = run_config(
            args.config, overrides, backend, force=args.force, cpus_per_task=args.cpus_per_task or 1
        )
    except ExperimentSkipped as why:
        print(f"skipped: {why}")
        return 0
    except SweepFailed as failed:
        _print_metrics(failed.metrics)
        if getattr(args, "debug", False):
            for label, failure in failed.failures:
                print(f"--- {label}:\n{failure.traceback or failure.summary}", file=sys.stderr)
        print(f"error: {one_line(failed)}", file=sys.stderr)
        return EXIT_RUNS_FAILED
    _print_metrics(metrics)
    return 0


def _demo(args: argparse.Namespace) -> int:
    if not args.bvh.is_file():
        raise UsageError(f"--bvh: expected an existing BVH file; got {str(args.bvh)!r}")
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
    written = ", ".join(str(args.out_dir / f) for f in ("metrics.json", "timings.json"))
    print(f"wrote {written} and {args.out_dir / 'alignment.png'}")
    return 0


def _summarise(args: argparse.Namespace) -> int:
    try:
        runs = load_runs(args.out_dir)
        metrics = [m for m in args.metrics.split(",") if m] if args.metrics else None
        over = [k for k in args.over.split(",") if k]
        page = results_markdown(
            args.title or args.out_dir.name,
            runs,
            metrics,
            over,
            source=f"python -m experiments summarise {args.out_dir}",
        )
    except SummariseError as err:
        raise UsageError(str(err)) from None
    if args.to is None:
        print(page, end="")
        return 0
    args.to.parent.mkdir(parents=True, exist_ok=True)
    args.to.write_text(page)
    print(f"wrote {args.to} ({len(runs)} runs)")
    return 0


def _command(args: argparse.Namespace) -> int:
    if args.command == "list":
        print(experiments_help(details=True))
        return 0
    if args.command == "summarise":
        return _summarise(args)
    retain_freed_memory()  # a process-wide allocator setting: see motion/runtime.py
    return _run(args) if args.command == "run" else _demo(args)


def main(argv: list[str] | None = None) -> int:
    """Run the command line (``argv`` without the program name); returns the exit status."""
    return run(_parser(), argv, _command)


if __name__ == "__main__":
    sys.exit(main())
