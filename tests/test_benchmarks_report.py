"""The benchmarks page (benchmarks/report.py): a script's rows become a table under a
provenance header, and a script that fails, times out or writes nothing is reported on the
page while the others still run. Fake scripts stand in for the real benchmarks (slow)."""

from __future__ import annotations

import importlib.util
import json
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report():
    spec = importlib.util.spec_from_file_location(
        "benchmarks_report", ROOT / "benchmarks/report.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


PROV = {
    "commit": "abc123",
    "dirty": True,
    "date": "2026-12-01T00:00:00+00:00",
    "machine": "box (x86_64)",
    "cpus": 2,
    "threads": 2,
    "python": "3.12.0",
    "torch": "2.13.0",
}

#: rows of a benchmark: higher and lower better, and one without an anchor
ROWS = [
    dict(case="SIZE | problem", ours="ours", value=250.0, anchor="theirs", anchor_value=100.0,
         units="items/s", better="higher"),
    dict(case="SIZE problem", ours="ours", value=2.0, anchor="theirs", anchor_value=10.0,
         units="s", better="lower"),
    dict(case="error", ours="ours", value=1234.5, anchor=None, anchor_value=None, units="px",
         better="lower"),
]  # fmt: skip

#: a benchmark that prints a line and writes :data:`ROWS`, SIZE telling whether it was quick
FAKE = f"""
import argparse, json
from pathlib import Path

parser = argparse.ArgumentParser()
parser.add_argument("--quick", action="store_true")
parser.add_argument("--json", type=Path)
args = parser.parse_args()
size = "small" if args.quick else "large"
print(f"fake printout ({{size}})")
rows = json.loads({json.dumps(json.dumps(ROWS))}.replace("SIZE", size))
args.json.write_text(json.dumps({{"rows": rows, "notes": ["a note"]}}))
"""


def _script(folder: Path, name: str, body: str) -> Path:
    path = folder / f"{name}.py"
    path.write_text(f'"""{name}: the first docstring line."""\n' + textwrap.dedent(body))
    return path


def test_rows_become_a_table_under_the_provenance(report):
    outcome = report.Outcome(
        "bench_fake",
        "bench_fake: the first docstring line.",
        "python benchmarks/bench_fake.py --quick",
        12.3,
        None,
        rows=[{**row, "case": row["case"].replace("SIZE", "quick")} for row in ROWS],
        notes=["a note"],
        stdout="fake printout\n",
    )
    page = report.benchmarks_markdown(
        [outcome], PROV, "python benchmarks/report.py --quick", quick=True
    )
    lines = page.splitlines()
    assert lines[0] == "# Benchmarks"
    assert "Regenerate: `python benchmarks/report.py --quick`" in lines
    assert "- commit: abc123 (with uncommitted changes)" in lines
    assert "- date: 2026-12-01T00:00:00+00:00" in lines
    assert "- machine: box (x86_64); cpus 2; torch threads 2; torch 2.13.0; python 3.12.0" in lines
    assert any(line.startswith("- sizes: quick") for line in lines)
    assert "- scripts: 1 run, 1 with figures" in lines
    table = lines.index("| case | ours | figure | anchor | figure | ours vs anchor |")
    assert lines[table + 2 : table + 5] == [
        "| quick \\| problem | ours | 250 items/s | theirs | 100 items/s | 2.50x |",  # higher
        "| quick problem | ours | 2 s | theirs | 10 s | 5.00x |",  # lower better: theirs / ours
        "| error | ours | 1,234 px | -- |  |  |",  # no anchor, no ratio
    ]
    assert "- a note" in lines and "fake printout" in lines
    assert "`python benchmarks/bench_fake.py --quick` (12 s)" in lines


def test_ratio_is_none_without_a_usable_anchor(report):
    row = dict(value=2.0, anchor="x", anchor_value=4.0, better="lower")
    assert report.ratio(row) == 2.0
    assert report.ratio({**row, "better": "higher"}) == 0.5
    assert report.ratio({**row, "anchor_value": None}) is None
    assert report.ratio({**row, "anchor_value": float("nan")}) is None
    assert report.ratio({**row, "value": 0.0}) is None
    assert report.ratio({**row, "anchor": None}) is None


def test_a_failing_benchmark_is_reported_and_the_rest_still_run(report, tmp_path):
    crash = _script(tmp_path, "bench_crash", "raise RuntimeError('the anchor is not installed')\n")
    silent = _script(tmp_path, "bench_silent", "print('forgot to write rows')\n")
    slow = _script(tmp_path, "bench_slow", "import time\ntime.sleep(60)\n")
    fake = _script(tmp_path, "bench_fake", FAKE)
    page = tmp_path / "docs" / "benchmarks.md"
    argv = [str(crash), str(silent), str(slow), str(fake), "--quick", "--timeout", "2"]
    assert report.main([*argv, "--to", str(page)]) == 1  # the page is written, and it says so
    text = page.read_text()
    assert text.startswith("# Benchmarks\n")
    assert "- commit: " in text and "torch threads" in text
    assert "- scripts: 4 run, 1 with figures, failed: bench_crash, bench_silent, bench_slow" in text
    sections = {s.split("\n", 1)[0]: s for s in text.split("\n## ")[1:]}
    assert "**Failed** (exit status 1)" in sections["bench_crash"]
    assert "RuntimeError: the anchor is not installed" in sections["bench_crash"]
    assert "no figures in its --json file" in sections["bench_silent"]
    assert "forgot to write rows" in sections["bench_silent"]
    assert "**Failed** (timed out after 2 s)" in sections["bench_slow"]
    fake_section = sections["bench_fake"]
    assert "bench_fake.py --quick` (" in fake_section  # --quick passed through
    assert "load average" in fake_section
    assert (
        "| small \\| problem | ours | 250 items/s | theirs | 100 items/s | 2.50x |" in fake_section
    )
    assert "fake printout (small)" in fake_section


def test_all_scripts_succeeding_exit_zero(report, tmp_path):
    fake = _script(tmp_path, "bench_fake", FAKE)
    page = tmp_path / "page.md"
    assert report.main([str(fake), "--to", str(page)]) == 0
    text = page.read_text()
    assert (
        "- sizes: full" in text and "| large problem | ours | 2 s | theirs | 10 s | 5.00x |" in text
    )
