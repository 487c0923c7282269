"""Sweeps in this process: records written as each run finishes, existing records of the same
resolved config not rerun (``--force`` reruns them), a failing entry reported by its label
while the rest finishes (exit status 1), an interrupted sweep resumed where it stopped, and
``--backend ray`` without Ray saying how to install it. (The Ray backend: test_sweeps_ray.py.)"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from experiments.__main__ import EXIT_RUNS_FAILED, main
from experiments.backends import Backend, SequentialBackend, make_backend
from experiments.runner import run_config
from tests.conftest import assert_message, cli_error_line
from tests.experiments import toy_experiment as toy

ROOT = Path(__file__).resolve().parents[2]
STICK_TIME = ROOT / "experiments" / "configs" / "stick_time.yaml"


@pytest.fixture
def toy_registered(monkeypatch):
    toy.register(monkeypatch)
    toy.CALLS.clear()
    yield
    toy.CALLS.clear()


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def _undated(files: dict[str, bytes]) -> dict[str, object]:
    """``files`` with each provenance record's date left out: a rerun records when it ran
    (to the second), the rest of its record is the same."""
    out: dict[str, object] = dict(files)
    for name, data in files.items():
        if name.endswith("provenance.json"):
            out[name] = {k: v for k, v in json.loads(data).items() if k != "date"}
    return out


def test_a_sweep_writes_each_record_and_the_combined_files(tmp_path, toy_registered):
    cfg = toy.write_config(tmp_path / "toy.yaml", ["{value: 1}", "{value: 2}"], tmp_path / "out")
    metrics = run_config(cfg)
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == [
        "metrics.json",
        "table.md",
        "timings.json",
        "value-1",
        "value-2",
    ]
    record = _files(out / "value-2")
    assert sorted(record) == [
        "config.yaml",
        "extra.md",
        "metrics.json",
        "per_frame.csv",
        "plot.png",
        "provenance.json",
        "table.md",
        "timings.json",
    ]
    assert record["plot.png"].startswith(b"toy (value-2): ")  # the title names the folder
    combined = json.loads((out / "metrics.json").read_text())
    assert set(combined) == {"score@value=1", "score@value=2", "threads@value=1", "threads@value=2"}
    assert json.loads((out / "timings.json").read_text()) == {
        "sec_per_run@value=1": 0.001,
        "sec_per_run@value=2": 0.001,
    }
    assert metrics == {**combined, "sec_per_run@value=1": 0.001, "sec_per_run@value=2": 0.001}
    table = (out / "table.md").read_text().splitlines()
    assert table[0] == "| run | score | threads |" and [r.split(" | ")[0] for r in table[2:]] == [
        "| value=1",
        "| value=2",
    ]


def test_existing_records_of_the_same_config_are_not_rerun_and_force_reruns(
    tmp_path, toy_registered, capsys
):
    cfg = toy.write_config(tmp_path / "toy.yaml", ["{value: 1}", "{value: 2}"], tmp_path / "out")
    out = tmp_path / "out"
    assert main(["run", str(cfg)]) == 0
    first = _files(out)
    assert toy.CALLS == {1.0: 1, 2.0: 1}
    capsys.readouterr()

    assert main(["run", str(cfg)]) == 0  # both records there: nothing runs, same files
    assert toy.CALLS == {1.0: 1, 2.0: 1} and _files(out) == first
    said = capsys.readouterr().out
    assert "2 of 2 runs already recorded with the same config, not rerun (--force reruns" in said

    (out / "value-2" / "metrics.json").unlink()  # an incomplete record is rerun
    assert main(["run", str(cfg)]) == 0
    assert toy.CALLS == {1.0: 1, 2.0: 2} and _undated(_files(out)) == _undated(first)

    assert main(["run", str(cfg), "seed=3"]) == 0  # another resolved config: both rerun
    assert toy.CALLS == {1.0: 2, 2.0: 3}
    assert (out / "metrics.json").read_bytes() != first["metrics.json"]
    assert "seed: 3" in (out / "value-1" / "config.yaml").read_text()

    assert main(["run", str(cfg), "seed=3", "--force"]) == 0
    assert toy.CALLS == {1.0: 3, 2.0: 4}


def test_a_config_without_a_sweep_is_resumable_too(tmp_path, toy_registered):
    cfg = toy.write_config(tmp_path / "toy.yaml", [], tmp_path / "out", value=5)
    first = run_config(cfg)
    assert run_config(cfg) == first and toy.CALLS == {5.0: 1}
    assert run_config(cfg, force=True) == first and toy.CALLS == {5.0: 2}
    assert run_config(cfg, {"value": 6})["score"] == first["score"] + 2


def test_a_failing_entry_is_named_and_the_rest_of_the_sweep_completes(tmp_path, capsys):
    """stick_time refuses a full cost matrix above full_matrix_max_cells (inside its run). The
    failing entry runs first; tiny runs a sweep's first and last entries, so the middle one is
    checked but not run."""
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(
        STICK_TIME.read_text().split("sweep:")[0]
        + "sweep:\n  - {full_matrix_max_cells: 1}\n  - {corrupt: false}\n  - {corrupt: true}\n"
    )
    out = tmp_path / "out"
    argv = [
        "run",
        str(cfg),
        "tiny=true",
        f"out_dir={out}",
        f"bvh={ROOT / 'motion/data/cmu_02_01_walk.bvh'}",
    ]
    assert main(argv) == EXIT_RUNS_FAILED
    std = capsys.readouterr()
    assert std.err.count("\n") == 1, std.err
    assert std.err.startswith(
        "error: stick_time: 1 of 2 runs failed: full_matrix_max_cells=1 (ConfigError: "
    )
    assert "use methods=[c2f] for long sequences" in std.err
    assert std.err.endswith(f"; the other runs' records are in {out}\n")
    # one line per finished run: the counts, then what finished
    assert re.search(
        r"^stick_time: sweep: 1/2 \(running 1, done 0, failed 1; \d+ s\) -- "
        r"full_matrix_max_cells=1: FAILED: ConfigError: full_matrix_max_cells=1: the full cost",
        std.out,
        re.M,
    ), std.out
    assert re.search(
        r"^stick_time: sweep: 2/2 \(running 0, done 1, failed 1; \d+ s\) -- "
        r"corrupt=True: done in \d+\.\d s$",
        std.out,
        re.M,
    ), std.out
    assert not (out / "corrupt-False").exists()  # tiny: the middle entry is not run
    assert (out / "corrupt-True" / "metrics.json").exists()
    assert not (out / "full_matrix_max_cells-1").exists()
    table = (out / "table.md").read_text().splitlines()
    assert [row.split(" | ")[0] for row in table[2:]] == ["| corrupt=True"]
    combined = json.loads((out / "metrics.json").read_text())
    assert {k.split("@")[1] for k in combined} == {"corrupt=True"}
    # the figures of the runs that finished are printed too
    assert "c_err_mean_robust@corrupt=True" in std.out

    # --debug: the failed run's traceback before the error line
    assert main([*argv, "--debug"]) == EXIT_RUNS_FAILED
    err = capsys.readouterr().err
    assert err.startswith("--- full_matrix_max_cells=1:\nTraceback (most recent call last):")


def test_an_interrupted_sweep_keeps_what_finished_and_resumes(tmp_path, toy_registered, capsys):
    cfg = toy.write_config(
        tmp_path / "toy.yaml",
        ["{value: 1}", "{value: 2, mode: interrupt}", "{value: 3}"],
        tmp_path / "out",
    )
    out = tmp_path / "out"
    assert main(["run", str(cfg)]) == 130  # Ctrl-C during the second run
    assert capsys.readouterr().err == "interrupted\n"
    assert set(json.loads((out / "metrics.json").read_text())) == {
        "score@value=1",
        "threads@value=1",
    }
    assert not (out / "value-3").exists()
    cfg.write_text(cfg.read_text().replace(", mode: interrupt", ""))
    assert main(["run", str(cfg)]) == 0
    assert toy.CALLS == {1.0: 1, 2.0: 2, 3.0: 1}
    assert len(json.loads((out / "metrics.json").read_text())) == 6


def test_a_failure_of_a_config_without_a_sweep_is_what_its_run_raised(
    tmp_path, toy_registered, capsys
):
    cfg = toy.write_config(tmp_path / "toy.yaml", [], tmp_path / "out", mode="raise")
    with pytest.raises(ValueError, match="the toy run was told to fail"):
        run_config(cfg)
    message = cli_error_line(capsys, main, ["run", str(cfg)])
    assert message == "value=1.0: the toy run was told to fail"
    assert not (tmp_path / "out" / "metrics.json").exists()


class _Recording(Backend):
    """The sequential backend, keeping the tasks it was given."""

    name = "recording"

    def __init__(self):
        self.tasks = []

    def run(self, tasks, work):
        self.tasks += tasks
        yield from SequentialBackend().run(tasks, work)


def test_each_entry_is_one_task_declaring_its_resources(tmp_path, toy_registered):
    cfg = toy.write_config(
        tmp_path / "toy.yaml", ["{value: 1}", "{value: 2, device: cuda}"], tmp_path / "out"
    )
    backend = _Recording()
    run_config(cfg, backend=backend, cpus_per_task=3)
    assert [(t.index, t.label, t.num_cpus, t.num_gpus) for t in backend.tasks] == [
        (0, "value=1", 3, 0),
        (1, "value=2,device=cuda", 3, 1),
    ]
    assert [t.item.config.value for t in backend.tasks] == [1.0, 2.0]


def test_backend_ray_without_ray_says_how_to_install_it(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    message = cli_error_line(
        capsys,
        main,
        ["run", str(STICK_TIME), "tiny=true", f"out_dir={tmp_path}", "--backend", "ray"],
    )
    assert message.startswith("--backend ray needs Ray, which is not installed (")
    assert message.endswith("install it with: pip install .[distributed]")
    assert not tmp_path.joinpath("metrics.json").exists()


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--address", "auto"], "--address: only with --backend ray; got --backend sequential"),
        (
            ["--cpus-per-task", "2"],
            "--cpus-per-task: only with --backend ray; got --backend sequential",
        ),
        (
            ["--backend", "ray", "--cpus-per-task", "0"],
            "python -m experiments run: argument --cpus-per-task: expected an integer >= 1; got 0 "
            "(see python -m experiments run --help)",
        ),
        (
            ["--backend", "dask"],
            "re:python -m experiments run: argument --backend: invalid choice: 'dask' "
            r"\(choose from '?sequential'?, '?ray'?\) \(see python -m experiments run --help\)",
        ),
    ],
)
def test_backend_options_are_checked(argv, expected, capsys, tmp_path):
    message = cli_error_line(capsys, main, ["run", str(STICK_TIME), f"out_dir={tmp_path}", *argv])
    assert_message(message, expected)


def test_make_backend_names_what_it_expected():
    assert make_backend("sequential").name == "sequential"
    with pytest.raises(ValueError, match="--backend must be one of sequential, ray; got 'dask'"):
        make_backend("dask")
