"""The Ray backend on a local Ray with 2 CPUs (started once for this module): the same records
as the sequential run, byte for byte; a failing entry and a killed worker reported by label
while the rest of the sweep finishes; torch threads sized to the task. Skipped without Ray
(``pip install .[distributed]``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from experiments.__main__ import EXIT_RUNS_FAILED, main
from experiments.backends import RayBackend
from experiments.runner import SweepFailed, run_config
from tests.experiments import toy_experiment as toy

ray = pytest.importorskip("ray")

ROOT = Path(__file__).resolve().parents[2]
STICK_TIME = ROOT / "experiments" / "configs" / "stick_time.yaml"
BVH = ROOT / "motion" / "data" / "cmu_02_01_walk.bvh"


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    """A local Ray of 2 CPUs for this module; the backends find it connected and use it."""
    if ray.is_initialized():  # pragma: no cover - another module left one running
        ray.shutdown()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def _files(folder: Path) -> dict[str, bytes]:
    return {
        p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def test_ray_writes_the_same_records_as_the_sequential_run(tmp_path):
    """stick_time tiny, two entries: every file of every record and the combined table and
    metrics.json are byte-identical (config.yaml differs only by its out_dir)."""
    overrides = {"tiny": True, "bvh": str(BVH)}
    seq, on_ray = tmp_path / "sequential", tmp_path / "ray"
    m_seq = run_config(STICK_TIME, {**overrides, "out_dir": str(seq)})
    m_ray = run_config(STICK_TIME, {**overrides, "out_dir": str(on_ray)}, backend=RayBackend())
    assert m_ray == m_seq
    a, b = _files(seq), _files(on_ray)
    assert sorted(a) == sorted(b)
    assert {
        "metrics.json",
        "table.md",
        "corrupt-True/plot.png",
        "corrupt-True/per_frame.csv",
    } <= set(a)
    for name in a:
        if name.endswith("config.yaml"):
            doc_a, doc_b = yaml.safe_load(a[name]), yaml.safe_load(b[name])
            assert doc_a.pop("out_dir") == str(seq) and doc_b.pop("out_dir") == str(on_ray)
            assert doc_a == doc_b, name
        elif name.endswith("provenance.json"):  # when it ran differs; from what does not
            prov_a, prov_b = json.loads(a[name]), json.loads(b[name])
            assert prov_a["commit"] == prov_b["commit"], name
        else:
            assert a[name] == b[name], name


def test_on_ray_a_failing_entry_is_named_and_the_rest_completes(tmp_path, capsys):
    cfg = tmp_path / "sweep.yaml"
    cfg.write_text(
        STICK_TIME.read_text().split("sweep:")[0]
        + "sweep:\n  - {corrupt: false}\n  - {full_matrix_max_cells: 1}\n"
    )
    out = tmp_path / "out"
    argv = ["run", str(cfg), "tiny=true", f"out_dir={out}", f"bvh={BVH}", "--backend", "ray"]
    assert main(argv) == EXIT_RUNS_FAILED
    std = capsys.readouterr()
    assert std.err.startswith(
        "error: stick_time: 1 of 2 runs failed: full_matrix_max_cells=1 (ConfigError: "
        "full_matrix_max_cells=1: the full cost matrix"
    )
    assert std.err.count("\n") == 1
    assert "stick_time: sweep: 2/2 (running 0, done 1, failed 1; " in std.out
    assert ") -- full_matrix_max_cells=1: FAILED: ConfigError: full_matrix_max_cells=1:" in std.out
    assert (out / "corrupt-False" / "metrics.json").exists()
    assert set(json.loads((out / "metrics.json").read_text())) == {
        k + "@corrupt=False"
        for k in json.loads((out / "corrupt-False" / "metrics.json").read_text())
    }


def test_on_ray_a_killed_worker_is_reported_and_the_rest_completes(tmp_path, monkeypatch):
    """The toy run SIGKILLs its worker for mode=kill: Ray retries it once (max_retries=1), it
    dies again, and it is reported by label; the other entry's record is written."""
    toy.register(monkeypatch)
    cfg = toy.write_config(
        tmp_path / "toy.yaml", ["{value: 1}", "{value: 2, mode: kill}"], tmp_path / "out"
    )
    with pytest.raises(SweepFailed) as failed:
        run_config(cfg, backend=RayBackend())
    message = str(failed.value)
    assert message.startswith(
        "toy: 1 of 2 runs failed: value=2,mode=kill (the worker died (ran 2 times): "
    ), message
    assert message.endswith(f"; the other runs' records are in {tmp_path / 'out'}")
    [(label, failure)] = failed.value.failures
    assert label == "value=2,mode=kill" and failure.worker_died and failure.exception is None
    assert (tmp_path / "out" / "value-1" / "metrics.json").exists()
    assert not (tmp_path / "out" / "value-2_mode-kill").exists()
    assert set(failed.value.metrics) == {"score@value=1", "threads@value=1", "sec_per_run@value=1"}


def test_on_ray_a_task_uses_as_many_torch_threads_as_it_has_cpus(tmp_path, monkeypatch):
    toy.register(monkeypatch)
    cfg = toy.write_config(tmp_path / "toy.yaml", ["{value: 1}", "{value: 2}"], tmp_path / "out")
    m = run_config(cfg, backend=RayBackend(), cpus_per_task=2)
    assert m["threads@value=1"] == m["threads@value=2"] == 2
    m = run_config(cfg, backend=RayBackend(), force=True)
    assert m["threads@value=1"] == m["threads@value=2"] == 1
