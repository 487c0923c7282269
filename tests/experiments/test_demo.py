"""The demo runs end to end on the bundled motion and its robust aligner beats the proposal's."""

import json

from experiments.__main__ import main
from experiments.demo import run_demo


def test_demo_writes_metrics_and_plot(tmp_path):
    metrics = run_demo(out_dir=tmp_path, seed=0)
    assert (tmp_path / "alignment.png").stat().st_size > 10_000
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    timings = json.loads((tmp_path / "timings.json").read_text())
    assert {**on_disk, **timings} == metrics and set(timings) == {
        f"seconds_{m}" for m in ("dtw", "chain", "robust")
    }
    # The proposal's DTW is dragged along the replaced frames; the robust chain is not.
    assert metrics["c_err_inside_mean_dtw"] > 10.0
    assert metrics["c_err_inside_mean_robust"] < 2.0
    assert metrics["c_err_outside_mean_robust"] < 1.0


def test_cli_demo(tmp_path, capsys):
    assert main(["demo", "--out-dir", str(tmp_path), "--seed", "1"]) == 0
    out = capsys.readouterr().out
    assert "robust chain" in out and "metrics.json" in out
