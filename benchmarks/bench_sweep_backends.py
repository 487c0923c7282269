"""A sweep of 8 entries run sequentially and on a local Ray, wall time of each, same run.

The sweep: ``experiments/configs/stick_time.yaml`` at full size (72 input frames against 343
reference frames) over seeds 0-3, with and without the replaced stretch -- 8 runs. Both
backends run as a user runs them, ``python -m experiments run CONFIG [--backend ray]``, each
into a fresh folder, so a wall time includes starting Python (and, on Ray, starting the
local Ray and its workers, and stopping it). Rounds alternate the order of the two; each line
shows the machine's load average before and after (other work on the machine shows there --
and Ray runs its workers at nice 15, so they yield to it). At the end the records of the two backends are compared: every file of every record and the combined
``metrics.json`` and ``table.md`` (``config.yaml`` differs only by its ``out_dir``,
``provenance.json`` only by when and on how many threads it ran: its commit is compared).

The local Ray has as many CPUs as the machine has cores; each task asks for 1 (and runs torch
on 1 thread); the sequential run uses torch's default threads (one per core).

Usage: python benchmarks/bench_sweep_backends.py [--rounds 1] [--seeds 4] [--quick] [--json PATH]
       (needs Ray: pip install .[distributed])

``--quick``: one seed (2 entries). ``--json PATH``: also write the figures as rows for
``benchmarks/report.py`` (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from report import parse_args, write_rows  # benchmarks/report.py, beside this script

ROOT = Path(__file__).resolve().parents[1]
STICK_TIME = ROOT / "experiments" / "configs" / "stick_time.yaml"
#: ``--quick``: fewer entries
QUICK = {"seeds": 1}


def _config(folder: Path, seeds: int) -> Path:
    """stick_time.yaml with its sweep replaced by seeds x corrupt (2 * seeds entries)."""
    head = STICK_TIME.read_text().split("sweep:")[0]
    entries = [
        f"  - {{seed: {s}, corrupt: {str(c).lower()}}}" for s in range(seeds) for c in (False, True)
    ]
    path = folder / "sweep.yaml"
    path.write_text(head + "sweep:\n" + "\n".join(entries) + "\n")
    return path


def _run(config: Path, out: Path, backend: str) -> float:
    cmd = [sys.executable, "-m", "experiments", "run", str(config), f"out_dir={out}"]
    cmd += ["--backend", backend]
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{backend} run failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return seconds


def _differences(a: Path, b: Path) -> list[str]:
    files_a = {p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file()}
    files_b = {p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file()}
    diff = sorted(files_a ^ files_b)
    for name in sorted(files_a & files_b):
        x, y = (a / name).read_bytes(), (b / name).read_bytes()
        if name.endswith("config.yaml"):  # out_dir differs by design
            x, y = (
                b"\n".join(line for line in t.splitlines() if not line.startswith(b"out_dir:"))
                for t in (x, y)
            )
        if name.endswith("provenance.json"):  # when and on how many threads differ by design
            x, y = (json.loads(t)["commit"] for t in (x, y))
        if x != y:
            diff.append(name)
    return diff


def main(argv: list[str] | None = None) -> list[dict]:
    """Runs the benchmark and prints its lines; returns its figures as rows (see
    ``benchmarks/report.py``), also written to ``--json`` when given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=1, help="alternating rounds of both")
    parser.add_argument("--seeds", type=int, default=4, help="seeds (entries = 2 x seeds)")
    args = parse_args(parser, QUICK, argv)
    import ray  # noqa: F401  (fail here, not after the sequential round, without Ray)
    import torch

    print(
        f"stick_time sweep of {2 * args.seeds} entries (seeds 0-{args.seeds - 1} x corrupt), "
        f"full size; {os.cpu_count()} cores, torch {torch.__version__} "
        f"({torch.get_num_threads()} threads in-process); local Ray with {os.cpu_count()} CPUs, "
        "1 CPU and 1 torch thread per task"
    )
    times: dict[str, list[float]] = {"sequential": [], "ray": []}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        config = _config(folder, args.seeds)
        for r in range(args.rounds):
            order = ("sequential", "ray") if r % 2 == 0 else ("ray", "sequential")
            for backend in order:
                out = folder / f"{backend}-{r}"
                before = os.getloadavg()[0]
                times[backend].append(_run(config, out, backend))
                print(
                    f"round {r}: {backend:<10} {times[backend][-1]:6.1f} s (load average "
                    f"{before:.1f} before, {os.getloadavg()[0]:.1f} after)",
                    flush=True,
                )
        diff = _differences(folder / "sequential-0", folder / "ray-0")
    best_seq, best_ray = min(times["sequential"]), min(times["ray"])
    print(
        f"wall time (best of {args.rounds}): sequential {best_seq:.1f} s, "
        f"Ray {best_ray:.1f} s ({best_seq / best_ray:.2f}x)"
    )
    if diff:
        print(f"records differ between the backends: {', '.join(diff)}")
    else:
        print(
            "records identical (every file; config.yaml but for out_dir, provenance.json's commit)"
        )
    results = [
        dict(
            case=f"stick_time sweep of {2 * args.seeds} entries, best of {args.rounds}",
            ours=f"local Ray, {os.cpu_count()} CPUs, 1 per task",
            value=best_ray,
            anchor="sequential, one process",
            anchor_value=best_seq,
            units="s wall",
            better="lower",
        )
    ]
    notes = [f"records differ between the backends: {', '.join(diff)}" if diff else
             "records of the two backends identical (but for out_dir and when they ran)"]  # fmt: skip
    return write_rows(args.json, results, notes)


if __name__ == "__main__":
    main()
