"""Results pages from run records: groups are the runs that differ only in their seeds, each
cell the mean and sample standard deviation of the group (checked against numpy), NaN left
out and counted, provenance read back as written."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from experiments.__main__ import main
from experiments.summarise import (
    SummariseError,
    group_runs,
    load_runs,
    provenance,
    results_markdown,
)


def _record(folder, config, metrics, timings=None, prov=None):
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text(
        yaml.safe_dump({"experiment": "x", "out_dir": "o", **config})
    )
    (folder / "metrics.json").write_text(json.dumps(metrics))
    if timings is not None:
        (folder / "timings.json").write_text(json.dumps(timings))
    if prov is not None:
        (folder / "provenance.json").write_text(json.dumps(prov))


@pytest.fixture
def sweep(tmp_path):
    rng = np.random.default_rng(0)
    values = {}
    for cams in (1, 2):
        for seed in (0, 1, 2):
            err = float(rng.normal(5 * cams, 1))
            values.setdefault(cams, []).append(err)
            agree = math.nan if (cams, seed) == (2, 1) else 0.5
            _record(
                tmp_path / f"cameras={cams},seed={seed}",
                {"cameras": cams, "seed": seed, "warp_seed": seed, "student": "a/b/07_01.bvh"},
                {"a_err": err, "agree": agree},
                {"sec": 1.0 + seed},
                {
                    "commit": "abc123",
                    "dirty": False,
                    "date": f"2026-12-0{seed + 1}T00:00:00+00:00",
                    "machine": "box (x86_64)",
                    "cpus": 2,
                    "threads": 2,
                    "torch": "2.13.0",
                },
            )
    return tmp_path, values


def test_groups_are_runs_differing_only_in_seeds(sweep):
    out, _ = sweep
    runs = load_runs(out)
    assert len(runs) == 6
    groups = group_runs(runs)
    assert [fields for fields, _ in groups] == [{"cameras": 1}, {"cameras": 2}]
    assert all(len(g) == 3 for _, g in groups)
    # grouping over nothing: every run its own group, told apart by its seeds
    assert len(group_runs(runs, over=())) == 6


def test_cells_are_mean_and_sample_std_and_count_nan(sweep):
    out, values = sweep
    page = results_markdown("cross", load_runs(out), ["a_err", "agree", "sec"])
    rows = [line for line in page.splitlines() if line.startswith("| cameras=")]
    assert len(rows) == 2
    for cams, row in zip((1, 2), rows, strict=True):
        cells = [c.strip() for c in row.strip("|").split("|")]
        mean, std = np.mean(values[cams]), np.std(values[cams], ddof=1)
        assert cells[2] == f"{mean:.3g} ± {std:.2g}"
        assert cells[4] == f"{2.0:.3g} ± {1.0:.2g}"  # the timing 1, 2, 3
    assert rows[0].split("|")[4].strip() == "0.5 ± 0"
    assert rows[1].split("|")[4].strip() == "0.5 ± 0 (n=2)"  # one NaN left out, said so
    assert "- commit: abc123" in page and "torch threads 2" in page
    assert "2026-12-01T00:00:00+00:00 .. 2026-12-03T00:00:00+00:00" in page


def test_errors_name_what_is_wrong(tmp_path, sweep):
    out, _ = sweep
    with pytest.raises(SummariseError, match="no run reports \\['nope'\\]"):
        results_markdown("x", load_runs(out), ["nope"])
    with pytest.raises(SummariseError, match="no run record"):
        empty = tmp_path / "empty"
        empty.mkdir()
        load_runs(empty)
    with pytest.raises(SummariseError, match="there is none"):
        load_runs(tmp_path / "missing")


def test_command_writes_the_page(sweep, tmp_path, capsys):
    out, _ = sweep
    page = tmp_path / "docs" / "results" / "cross.md"
    assert main(["summarise", str(out), "--metrics", "a_err", "--to", str(page)]) == 0
    assert page.read_text().startswith("# ") and "| cameras=2 | 3 |" in page.read_text()
    assert main(["summarise", str(tmp_path / "missing")]) == 2
    assert "there is none" in capsys.readouterr().err


def test_provenance_of_this_checkout():
    p = provenance()
    assert len(p["commit"]) == 40 or p["commit"] == "unknown"
    assert p["threads"] >= 1 and p["cpus"] >= 1 and p["torch"]
