"""Results pages from run records: ``python -m experiments summarise OUT_DIR``.

A run's record (:mod:`experiments.runner`) is a folder with ``metrics.json``, maybe
``timings.json``, ``config.yaml`` (the resolved config) and ``provenance.json`` (where and
from what it ran: :func:`motion.provenance.provenance`, re-exported here). A sweep's
``out_dir`` holds one such folder per entry.
This module reads them back and writes one Markdown page: a provenance header (commits,
dates, machines, threads), then a table with a row per group of runs that differ only in
their seeds (by default ``seed`` and ``warp_seed``), each metric as mean +- standard
deviation over the group's runs (sample standard deviation; NaN values left out and the
count of finite ones shown where it is not the group's size). The page is generated: rerun
the sweep, rerun this, and the numbers and their provenance change together.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

from motion.provenance import provenance

__all__ = [
    "RunResult",
    "SummariseError",
    "group_runs",
    "load_runs",
    "provenance",
    "provenance_lines",
    "results_markdown",
    "write_page",
]

#: config keys that make repetitions of one experiment rather than different experiments
SEED_KEYS = ("seed", "warp_seed")
#: config keys that never tell two runs apart (where the record went, a quick run)
IGNORED_KEYS = ("out_dir", "tiny", "experiment")


class SummariseError(ValueError):
    """Records that cannot be read or summarised (the message names the folder)."""


@dataclass(frozen=True)
class RunResult:
    """One run's record read back: its folder, resolved config (without the keys in
    :data:`IGNORED_KEYS`), figures (accuracy and timings together), which of them are
    timings, and its provenance (``None``: the record predates provenance)."""

    folder: Path
    config: dict
    metrics: dict[str, float]
    timing_names: frozenset[str]
    provenance: dict | None


def _read_json(path: Path) -> dict:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise SummariseError(f"{path}: cannot read it as JSON ({err})") from None
    if not isinstance(value, dict):
        raise SummariseError(f"{path}: expected a JSON object; got {type(value).__name__}")
    return value


def _read_run(folder: Path) -> RunResult:
    try:
        config = yaml.safe_load((folder / "config.yaml").read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        raise SummariseError(f"{folder}: no readable config.yaml ({err})") from None
    metrics = _read_json(folder / "metrics.json")
    timings = _read_json(folder / "timings.json") if (folder / "timings.json").exists() else {}
    prov = _read_json(folder / "provenance.json") if (folder / "provenance.json").exists() else None
    config = {k: v for k, v in config.items() if k not in IGNORED_KEYS}
    return RunResult(folder, config, {**metrics, **timings}, frozenset(timings), prov)


def load_runs(out_dir: str | Path) -> list[RunResult]:
    """The complete records under ``out_dir``: the folder itself when it is one run's
    record, else each sub-folder holding ``metrics.json`` and ``config.yaml`` (a sweep's
    runs), in name order.

    Raises:
        SummariseError: no such folder, or no complete record in it.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise SummariseError(f"{out}: expected a folder of run records; there is none")
    if (out / "config.yaml").exists() and not any(p.is_dir() for p in out.iterdir()):
        return [_read_run(out)]
    folders = sorted(
        p for p in out.iterdir() if (p / "metrics.json").exists() and (p / "config.yaml").exists()
    )
    if not folders:
        raise SummariseError(f"{out}: no run record in it (a folder with metrics.json)")
    return [_read_run(p) for p in folders]


def _key(value) -> str:
    return json.dumps(value, sort_keys=True)


def group_runs(
    runs: Sequence[RunResult], over: Iterable[str] = SEED_KEYS
) -> list[tuple[dict, list[RunResult]]]:
    """Runs grouped by their config without the keys ``over`` (the repetitions): a list of
    (what tells the group apart -- only the keys whose values differ between groups --,
    its runs), ordered by those values."""
    over = set(over)
    groups: dict[str, list[RunResult]] = {}
    for run in runs:
        rest = {k: v for k, v in run.config.items() if k not in over}
        groups.setdefault(_key(rest), []).append(run)
    keys = sorted({k for run in runs for k in run.config} - over)
    varying = [k for k in keys if len({_key(r.config.get(k)) for r in runs}) > 1]
    out = [({k: g[0].config.get(k) for k in varying}, g) for g in groups.values()]
    return sorted(out, key=lambda fg: _key(list(fg[0].values())))


def _mean_std(values: list[float]) -> tuple[float, float, int]:
    finite = [v for v in values if isinstance(v, int | float) and math.isfinite(v)]
    n = len(finite)
    if n == 0:
        return math.nan, math.nan, 0
    mean = sum(finite) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1)) if n > 1 else math.nan
    return mean, std, n


def _cell(values: list[float], size: int) -> str:
    mean, std, n = _mean_std(values)
    if n == 0:
        return "--"
    text = f"{mean:.3g}" if math.isnan(std) else f"{mean:.3g} ± {std:.2g}"
    return text if n == size else f"{text} (n={n})"


def _label(fields: dict) -> str:
    def short(v) -> str:
        return Path(v).stem if isinstance(v, str) and v.endswith(".bvh") else str(v)

    return ", ".join(f"{k}={short(v)}" for k, v in fields.items()) or "all"


def write_page(text: str, to: str | Path | None) -> None:
    """A generated results page to the file ``to``, or to standard output (``None``)."""
    if to:
        Path(to).write_text(text)
    else:
        print(text)


def page_main(
    argv: Sequence[str] | None,
    prog: str,
    description: str,
    page: Callable[[list[str]], str],
    figure: Callable[[list[str], str], None] | None = None,
) -> int:
    """The command line of an analysis that reads folders of run records and writes one
    results page: ``prog RUNS [RUNS ...] [--to PAGE]`` (and ``[--figure PNG]`` when the
    analysis draws one). ``page(folders)`` makes the page's text, ``figure(folders, path)``
    draws the figure; a :class:`SummariseError` either raises is printed as one line and
    exits 2."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("runs", nargs="+", help="folders of register_synthetic run records")
    parser.add_argument("--to", help="write the results page here (Markdown)")
    if figure is not None:
        parser.add_argument("--figure", help="also draw the analysis's figure here (PNG)")
    args = parser.parse_args(argv)
    try:
        text = page(args.runs)
        if figure is not None and args.figure:
            figure(args.runs, args.figure)
    except SummariseError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    write_page(text, args.to)
    return 0


def provenance_lines(runs: Sequence[RunResult]) -> list[str]:
    """The provenance of ``runs`` as Markdown list items: how many, commits (and whether any
    ran with uncommitted changes), dates, machines and threads."""
    known = [r.provenance for r in runs if r.provenance is not None]
    missing = len(runs) - len(known)

    def values(field: str) -> str:
        return ", ".join(sorted({str(p.get(field)) for p in known})) or "not recorded"

    dates = sorted(str(p.get("date")) for p in known)
    lines = [
        f"- runs: {len(runs)}" + (f" ({missing} without a provenance record)" if missing else ""),
        f"- commit: {values('commit')}"
        + (" (with uncommitted changes)" if any(p.get("dirty") for p in known) else ""),
        f"- dates: {dates[0]} .. {dates[-1]}" if dates else "- dates: not recorded",
        f"- machine: {values('machine')}; cpus {values('cpus')}; torch threads "
        f"{values('threads')}; torch {values('torch')}",
    ]
    return lines


def results_markdown(
    title: str,
    runs: Sequence[RunResult],
    metrics: Sequence[str] | None = None,
    over: Iterable[str] = SEED_KEYS,
    source: str = "",
) -> str:
    """The results page of ``runs``: ``title``, the provenance, then a row per
    :func:`group_runs` group and a column per metric (``metrics``: those names in that
    order; ``None``: every accuracy metric the runs report, then every timing), mean ±
    std over the group. ``source``: the command or config that made the runs, quoted on the
    page.

    Raises:
        SummariseError: a metric no run reports.
    """
    over = tuple(over)
    every = sorted({k for r in runs for k in r.metrics})
    if metrics is None:
        timing = set().union(*(r.timing_names for r in runs))
        metrics = [k for k in every if k not in timing] + [k for k in every if k in timing]
    unknown = [m for m in metrics if m not in every]
    if unknown:
        raise SummariseError(f"no run reports {unknown}; they report {every}")
    groups = group_runs(runs, over)
    lines = [f"# {title}", "", "Generated by `python -m experiments summarise` from run records."]
    if source:
        lines += ["", f"Source: `{source}`"]
    lines += ["", *provenance_lines(runs), ""]
    lines.append(
        f"Each cell: mean ± standard deviation over the runs that differ only in {', '.join(over)}."
    )
    lines += ["", "| runs | n | " + " | ".join(metrics) + " |", "|---|---|" + "---|" * len(metrics)]
    for fields, group in groups:
        cells = [_cell([r.metrics.get(m, math.nan) for r in group], len(group)) for m in metrics]
        lines.append(f"| {_label(fields)} | {len(group)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
