"""The benchmarks page: runs every benchmark script and writes ``docs/benchmarks.md`` from
their own measurements (``make bench``).

Usage: python benchmarks/report.py [--quick] [--to docs/benchmarks.md] [--timeout S]
       [SCRIPT ...]

Each script (default: every ``benchmarks/bench_*.py``, in name order) runs in its own
process, ``python SCRIPT --json FILE [--quick]``, and writes the figures it prints as rows
(JSON: ``{"rows": [...], "notes": [...]}``), each row

    {"case": "1000 x 5000, with path", "ours": "chain f32", "value": 178.0,
     "anchor": "dtaidistance", "anchor_value": 70.0, "units": "Mcells/s", "better": "higher"}

(``anchor`` and ``anchor_value`` ``null`` where the figure has no anchor; ``better``:
``"higher"`` or ``"lower"``). The page has a provenance header (commit, uncommitted changes
or not, date, machine, CPUs, torch threads, torch and Python versions:
:func:`motion.provenance.provenance`), then per script a table of our figure beside the
anchor's and their ratio, its printout, and the command that regenerates the page. A script
that fails, times out or writes no figures is reported on the page with the end of its
output, and the others still run; the exit status is then 1 (the page is written either way).

``--quick`` passes ``--quick`` to every script: each one's smaller problem (fewer frames,
hypotheses or timed rounds; see each script's ``--help``). The scripts take both options
with :func:`parse_args` and write their rows with :func:`write_rows` (``from report import
...``: a script's own folder is first on its ``sys.path``).
"""

from __future__ import annotations

import argparse
import ast
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from motion.provenance import provenance

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "benchmarks.md"
#: the end of a script's output quoted on the page
TAIL_LINES = 40


@dataclass
class Outcome:
    """One script's run: its name, its docstring's first paragraph, the command as shown on
    the page, wall seconds, ``error`` (why it has no figures, ``None`` when it has them), its
    rows and notes (see the module's docstring), what it wrote to stdout and stderr, and the
    machine's 1-minute load average before and after it ran (other work on the machine
    shows there: a shared machine's figures are only as good as its quiet)."""

    name: str
    description: str
    command: str
    seconds: float
    error: str | None
    rows: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    stdout: str = ""
    stderr: str = ""
    load: tuple[float, float] | None = None


def parse_args(
    parser: argparse.ArgumentParser, quick: dict, argv: Sequence[str] | None = None
) -> argparse.Namespace:
    """A benchmark script's options: ``parser``'s own, ``--quick`` (``quick``: the option
    values of its smaller problem; options given explicitly still win) and ``--json PATH``
    (where :func:`write_rows` writes)."""
    parser.add_argument("--quick", action="store_true", help=f"a smaller run: {quick}")
    parser.add_argument("--json", type=Path, help="also write the figures here as JSON rows")
    args = parser.parse_args(argv)
    if args.quick:
        parser.set_defaults(**quick)
        args = parser.parse_args(argv)
    return args


def write_rows(path: Path | None, rows: list[dict], notes: Sequence[str] = ()) -> list[dict]:
    """Writes a script's ``rows`` and ``notes`` to ``path`` as :func:`run_benchmark` reads
    them (nothing where ``path`` is ``None``); returns ``rows``."""
    if path is not None:
        path.write_text(json.dumps({"rows": rows, "notes": list(notes)}, indent=2) + "\n")
    return rows


def _description(script: Path) -> str:
    """The first paragraph of the script's docstring, on one line."""
    try:
        doc = ast.get_docstring(ast.parse(script.read_text()))
    except (OSError, SyntaxError, ValueError):
        return ""
    return " ".join((doc or "").split("\n\n")[0].split())


def _shown(script: Path, args: Sequence[str]) -> str:
    """The command as a reader runs it from the repository root."""
    try:
        path = script.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        path = str(script)
    return " ".join(["python", path, *args])


def run_benchmark(script: Path, quick: bool = False, timeout: float = 3600.0) -> Outcome:
    """Runs ``script`` in its own process (from the repository root, with this Python) and
    reads back the rows it writes with ``--json``; never raises for the script's own failure
    (a non-zero exit status, a timeout, no or unreadable JSON: the outcome's ``error``)."""
    script = Path(script)
    extra = ["--quick"] if quick else []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.json"
        cmd = [sys.executable, str(script), *extra, "--json", str(out)]
        before = _load()
        start = time.perf_counter()
        # a session of its own, so that a timeout stops its children too (Ray's workers)
        proc = subprocess.Popen(
            cmd,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        try:
            stdout, stderr = proc.communicate(timeout=timeout)
            error = None if proc.returncode == 0 else f"exit status {proc.returncode}"
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            stdout, stderr = proc.communicate()
            error = f"timed out after {timeout:g} s"
        seconds = time.perf_counter() - start
        after = _load()
        load = None if before is None or after is None else (before, after)
        rows, notes = [], []
        if error is None:
            try:
                data = json.loads(out.read_text())
                rows, notes = list(data["rows"]), list(data.get("notes", []))
            except (OSError, ValueError, KeyError, TypeError) as err:
                error = f"exit status 0 but no figures in its --json file ({err})"
    shown = _shown(script, extra)
    return Outcome(
        script.stem, _description(script), shown, seconds, error, rows, notes, stdout, stderr, load
    )


def _load() -> float | None:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):  # not on this platform
        return None


def ratio(row: dict) -> float | None:
    """How many times better our figure is than the anchor's (> 1: ours better): ours over
    the anchor's where higher is better, the anchor's over ours where lower is; ``None``
    without an anchor or where either figure is missing, zero or not finite."""
    ours, theirs = row.get("value"), row.get("anchor_value")
    if row.get("anchor") is None or not _finite(ours) or not _finite(theirs):
        return None
    if ours == 0 or theirs == 0:
        return None
    return ours / theirs if row.get("better", "higher") == "higher" else theirs / ours


def _finite(value) -> bool:
    return isinstance(value, int | float) and math.isfinite(value)


def _figure(value, units: str) -> str:
    if not _finite(value):
        return "--"
    if abs(value) >= 1000:
        text = f"{value:,.0f}"
    elif abs(value) >= 100:
        text = f"{value:.0f}"
    else:
        text = f"{value:.3g}"
    return f"{text} {units}".strip()


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _table(rows: list[dict]) -> list[str]:
    lines = [
        "| case | ours | figure | anchor | figure | ours vs anchor |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        units = row.get("units", "")
        r = ratio(row)
        cells = [
            row.get("case", ""),
            row.get("ours", ""),
            _figure(row.get("value"), units),
            row.get("anchor") or "--",
            _figure(row.get("anchor_value"), units) if row.get("anchor") else "",
            "" if r is None else (f"{r:.2f}x" if r < 100 else f"{r:,.0f}x"),
        ]
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return lines


def _provenance_lines(prov: dict) -> list[str]:
    dirty = {True: " (with uncommitted changes)", None: " (unknown whether changed)"}
    return [
        f"- commit: {prov.get('commit')}{dirty.get(prov.get('dirty'), '')}",
        f"- date: {prov.get('date')}",
        f"- machine: {prov.get('machine')}; cpus {prov.get('cpus')}; torch threads "
        f"{prov.get('threads')}; torch {prov.get('torch')}; python {prov.get('python')}",
    ]


def benchmarks_markdown(
    outcomes: Sequence[Outcome], prov: dict, command: str, quick: bool = False
) -> str:
    """The benchmarks page: the provenance ``prov`` (:func:`motion.provenance.provenance`),
    the command that regenerates the page, then a section per outcome: its table of our
    figures beside the anchors' (or why it has none) and its printout."""
    failed = [o.name for o in outcomes if o.error is not None]
    lines = [
        "# Benchmarks",
        "",
        "Generated by `benchmarks/report.py` from the benchmark scripts' own measurements: "
        "do not edit, rerun it.",
        "",
        f"Regenerate: `{command}`" + ("" if quick else " (or `make bench`)"),
        "",
        *_provenance_lines(prov),
        "- sizes: "
        + (
            "quick (`--quick`: each script's smaller problem; `make bench` runs the full ones)"
            if quick
            else "full (each script's defaults)"
        ),
        f"- scripts: {len(outcomes)} run, {len(outcomes) - len(failed)} with figures"
        + (f", failed: {', '.join(failed)}" if failed else ""),
        f"- wall time: {sum(o.seconds for o in outcomes):.0f} s",
        "",
        "Each table: our figure beside the anchor's, measured by the same script in the same "
        "run; *ours vs anchor* is how many times better ours is (> 1: ours better), ours "
        "over the anchor's where higher is better, the anchor's over ours where lower is. "
        f"Beside each command, the machine's 1-minute load average (it has {prov.get('cpus')} "
        "CPUs: a load above that means other work shared them, and the figures suffer).",
    ]
    for o in outcomes:
        lines += ["", f"## {o.name}", ""]
        if o.description:
            lines += [o.description, ""]
        load = f"; load average {o.load[0]:.1f} before, {o.load[1]:.1f} after" if o.load else ""
        lines.append(f"`{o.command}` ({o.seconds:.0f} s{load})")
        lines.append("")
        if o.error is None:
            lines += _table(o.rows) if o.rows else ["(no figures)"]
            lines += ([""] + [f"- {note}" for note in o.notes]) if o.notes else []
            printout = o.stdout.rstrip().splitlines()[-TAIL_LINES:]
            if printout:
                summary = "<details><summary>its printout</summary>"
                lines += ["", summary, "", "```", *printout, "```", "", "</details>"]
        else:
            output = (o.stdout.rstrip() + "\n" + o.stderr.rstrip()).strip()
            lines.append(f"**Failed** ({o.error}): no figures. The end of its output:")
            lines += ["", "```", *output.splitlines()[-TAIL_LINES:], "```"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scripts", nargs="*", type=Path, help="default: benchmarks/bench_*.py")
    parser.add_argument("--quick", action="store_true", help="each script's smaller problem")
    parser.add_argument("--to", type=Path, default=PAGE, help="the page (default: %(default)s)")
    parser.add_argument(
        "--timeout", type=float, default=3600.0, help="seconds per script (default: %(default)s)"
    )
    args = parser.parse_args(argv)
    scripts = args.scripts or sorted(Path(__file__).resolve().parent.glob("bench_*.py"))
    prov = provenance(ROOT)
    given = sys.argv[1:] if argv is None else list(argv)
    command = " ".join(["python benchmarks/report.py", *given])
    outcomes = []
    for script in scripts:
        print(f"{Path(script).stem} ...", end=" ", flush=True)
        outcome = run_benchmark(script, args.quick, args.timeout)
        outcomes.append(outcome)
        print(f"{outcome.seconds:.0f} s, " + (outcome.error or f"{len(outcome.rows)} rows"))
    args.to.parent.mkdir(parents=True, exist_ok=True)
    args.to.write_text(benchmarks_markdown(outcomes, prov, command, args.quick))
    print(f"wrote {args.to}")
    return 1 if any(o.error is not None for o in outcomes) else 0


if __name__ == "__main__":
    sys.exit(main())
