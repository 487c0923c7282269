"""Run a config: one result record per run, written where tables and plots are made from it.

Each run writes into its ``out_dir``: ``metrics.json`` (flat: metric name -> number, the
accuracy figures only, so the same config and seed give a byte-identical file),
``timings.json`` (the experiment's timing figures, e.g. ``poses_per_s``, which vary from run
to run; only for experiments that measure any), ``config.yaml`` (the resolved config),
``provenance.json`` (commit, date, machine, threads: :func:`motion.provenance.provenance`),
``per_frame.csv`` where the experiment has per-frame values, ``plot.png`` and ``table.md``. A
config with a ``sweep`` runs once per entry (into ``out_dir/<label>``) and also writes the
combined ``table.md``, ``metrics.json`` and ``timings.json`` (keys suffixed ``@label``) in
``out_dir``. Progress goes to stdout (see :mod:`experiments.progress`).

Where the runs execute is a backend's business (:mod:`experiments.backends`: in this process,
or one Ray task per run). Either way a run is :func:`execute` -- the experiment, then its
record rendered to bytes (:class:`RunRecord`) -- and this process writes the record
(:func:`write_record`), so both backends write the same files. The combined files are
rewritten, in sweep order, after every run that finishes: an interrupted sweep keeps what
finished. A run whose folder already holds a complete record of the same resolved config
(:func:`existing_record`) is not run again unless ``force``; a failed run is reported by its
label, the others go on, and :class:`SweepFailed` names what failed at the end.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import re
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import yaml

from experiments import (
    nbp_ablation,
    nbp_noise_sweep,
    nbp_single_image,
    polish_basin,
    pose2sim_real,
    register_long,
    register_real,
    register_synthetic,
    stage1_draws,
    stick_pose,
    stick_time,
)
from experiments.backends import Backend, Failure, SequentialBackend, Task
from experiments.config import (
    ExperimentConfig,
    ExperimentSkipped,
    apply_overrides,
    load_config,
    sweep_label,
)
from experiments.progress import Tally, note
from motion.provenance import provenance

__all__ = [
    "CONFIGS",
    "EXPERIMENTS",
    "Experiment",
    "RunRecord",
    "RunRequest",
    "SweepFailed",
    "execute",
    "existing_record",
    "run_config",
    "split_timings",
    "write_record",
]

#: the shipped config files
CONFIGS = Path(__file__).resolve().parent / "configs"


class Experiment(NamedTuple):
    """A registered experiment: its config schema, ``run(cfg) -> (metrics, per-frame
    columns, plot data)``, ``plot(path, data, title)``, and the names of its metrics that
    are timings (written to ``timings.json``, apart from the accuracy figures)."""

    schema: type
    run: Callable
    plot: Callable
    timings: tuple[str, ...] = ()


#: experiment name -> Experiment
EXPERIMENTS = {
    "stick_time": Experiment(stick_time.StickTimeConfig, stick_time.run, stick_time.plot),
    "stick_pose": Experiment(
        stick_pose.StickPoseConfig, stick_pose.run, stick_pose.plot, stick_pose.TIMINGS
    ),
    "pose2sim_real": Experiment(
        pose2sim_real.Pose2simRealConfig, pose2sim_real.run, pose2sim_real.plot
    ),
    "nbp_ablation": Experiment(
        nbp_ablation.NbpAblationConfig, nbp_ablation.run, nbp_ablation.plot, nbp_ablation.TIMINGS
    ),
    "nbp_noise_sweep": Experiment(
        nbp_noise_sweep.NbpNoiseSweepConfig,
        nbp_noise_sweep.run,
        nbp_noise_sweep.plot,
        nbp_noise_sweep.TIMINGS,
    ),
    "nbp_single_image": Experiment(
        nbp_single_image.NbpSingleImageConfig,
        nbp_single_image.run,
        nbp_single_image.plot,
        nbp_single_image.TIMINGS,
    ),
    "register_synthetic": Experiment(
        register_synthetic.RegisterSyntheticConfig,
        register_synthetic.run,
        register_synthetic.plot,
        register_synthetic.TIMINGS,
    ),
    "register_long": Experiment(
        register_long.RegisterLongConfig,
        register_long.run,
        register_long.plot,
        register_long.TIMINGS,
    ),
    "register_real": Experiment(
        register_real.RegisterRealConfig,
        register_real.run,
        register_real.plot,
        register_real.TIMINGS,
    ),
    "polish_basin": Experiment(polish_basin.PolishBasinConfig, polish_basin.run, polish_basin.plot),
    "stage1_draws": Experiment(
        stage1_draws.Stage1DrawsConfig, stage1_draws.run, stage1_draws.plot, stage1_draws.TIMINGS
    ),
}


def split_timings(metrics: dict, timings: tuple[str, ...]) -> tuple[dict, dict]:
    """``metrics`` -> (accuracy figures, timing figures), by the names in ``timings`` (a
    sweep's ``name@label`` keys go by their ``name``)."""
    accuracy, timing = {}, {}
    for key, value in metrics.items():
        (timing if key.split("@", 1)[0] in timings else accuracy)[key] = value
    return accuracy, timing


def _json(values: dict) -> str:
    return json.dumps(values, indent=2, sort_keys=True) + "\n"


def _table(header: str, values: dict) -> list[str]:
    return [f"| {header} | value |", "|---|---|"] + [
        f"| {k} | {v:.4g} |" for k, v in sorted(values.items())
    ]


def _dir_name(label: str) -> str:
    """A sweep entry's folder: its label with ``=`` -> ``-``, ``,`` -> ``_`` and anything
    that is not a plain file-name character (``/`` included) -> ``_``."""
    return re.sub(r"[^\w.+-]", "_", label.replace("=", "-").replace(",", "_"))


def _write_json(out: Path, accuracy: dict, timing: dict) -> None:
    (out / "metrics.json").write_text(_json(accuracy))
    if timing:
        (out / "timings.json").write_text(_json(timing))


def _write_atomic(path: Path, data: bytes) -> None:
    """``data`` into ``path`` through a temporary file beside it, so an interrupted write
    leaves the old file or the new one, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _config_doc(name: str, cfg) -> dict:
    """What ``config.yaml`` holds: the experiment's name and every field of the resolved
    config."""
    return {"experiment": name, **dataclasses.asdict(cfg)}


def _write_run(
    out: Path, name: str, cfg, metrics: dict, exp: Experiment, columns, plot_data, title
):
    out.mkdir(parents=True, exist_ok=True)
    accuracy, timing = split_timings(metrics, exp.timings)
    _write_json(out, accuracy, timing)
    (out / "config.yaml").write_text(yaml.safe_dump(_config_doc(name, cfg), sort_keys=False))
    (out / "provenance.json").write_text(json.dumps(provenance(), indent=2) + "\n")
    if columns:
        keys = list(columns)
        with open(out / "per_frame.csv", "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(keys)
            for row in zip(*(columns[k] for k in keys), strict=True):
                writer.writerow([int(v) if float(v).is_integer() else float(v) for v in row])
    exp.plot(out / "plot.png", plot_data, title)
    lines = _table("metric", accuracy) + (["", *_table("timing", timing)] if timing else [])
    (out / "table.md").write_text("\n".join(lines) + "\n")


# ------------------------------------------------------------------------ one run's record

#: the files a record may hold that the runner writes itself (the plot may add others)
RECORD_FILES = (
    "metrics.json",
    "timings.json",
    "config.yaml",
    "provenance.json",
    "per_frame.csv",
    "plot.png",
    "table.md",
)


@dataclass(frozen=True)
class RunRequest:
    """One run as a worker gets it: the experiment (``name`` and its registry entry), the
    resolved config, the sweep entry's label (announced when the run starts; ``None`` for a
    config without a sweep) and the title of its plot."""

    name: str
    experiment: Experiment
    config: ExperimentConfig
    label: str | None
    title: str


@dataclass(frozen=True)
class RunRecord:
    """One run's record, made where it ran: ``metrics`` (accuracy and timing figures
    together, as the experiment returned them) and ``files`` (path relative to the record's
    folder -> bytes: ``metrics.json``, ``config.yaml``, ``per_frame.csv``, ``plot.png``,
    ``table.md``, maybe ``timings.json`` and whatever the plot writes beside it). Files, not
    plot data, travel back from a worker: plot data may be large or not pickle, and the
    parent writes the same bytes either way."""

    metrics: dict[str, float]
    files: dict[str, bytes]


def execute(request: RunRequest) -> RunRecord:
    """Run ``request`` and render its record in a temporary folder; returns it as bytes.
    The work function of both backends (a Ray worker may have no access to ``out_dir``)."""
    if request.label is not None:
        note(f"{request.name}: run {request.label}")
    exp = request.experiment
    metrics, columns, plot_data = exp.run(request.config)
    with tempfile.TemporaryDirectory(prefix="record-") as tmp:
        out = Path(tmp) / "record"
        _write_run(
            out, request.name, request.config, metrics, exp, columns, plot_data, request.title
        )
        files = {
            p.relative_to(out).as_posix(): p.read_bytes()
            for p in sorted(out.rglob("*"))
            if p.is_file()
        }
    return RunRecord(metrics, files)


def write_record(out: Path, record: RunRecord) -> None:
    """``record``'s files into the folder ``out``, ``metrics.json`` last (its presence marks a
    complete record: it is removed first and written atomically), and the runner's files
    of an older record that this one lacks removed (a stale ``timings.json``)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").unlink(missing_ok=True)
    for rel, data in record.files.items():
        if rel != "metrics.json":
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            _write_atomic(out / rel, data)
    for stale in set(RECORD_FILES) - set(record.files):
        (out / stale).unlink(missing_ok=True)
    _write_atomic(out / "metrics.json", record.files["metrics.json"])


def existing_record(out: Path, name: str, cfg) -> dict[str, float] | None:
    """The figures (accuracy and timings) of the record in ``out`` when it is complete
    (``metrics.json`` there) and was made by the same resolved config (its ``config.yaml``
    reads as ``cfg`` does); ``None`` otherwise."""
    try:
        saved = yaml.safe_load((out / "config.yaml").read_text())
        metrics = json.loads((out / "metrics.json").read_text())
        timings_file = out / "timings.json"
        timings = json.loads(timings_file.read_text()) if timings_file.exists() else {}
    except (OSError, ValueError, yaml.YAMLError):
        return None
    expected = yaml.safe_load(yaml.safe_dump(_config_doc(name, cfg), sort_keys=False))
    if saved != expected or not isinstance(metrics, dict) or not isinstance(timings, dict):
        return None
    return {**metrics, **timings}


# ------------------------------------------------------------------------------ the sweep


class SweepFailed(RuntimeError):
    """Some runs of a config failed (the others' records are written): ``failures`` lists
    (label, :class:`~experiments.backends.Failure`) in sweep order; ``metrics`` holds the
    figures of the runs that finished (as :func:`run_config` returns them)."""

    def __init__(self, message: str, failures: list[tuple[str, Failure]], metrics: dict):
        super().__init__(message)
        self.failures, self.metrics = failures, metrics


def _write_combined(out: Path, rows: list[tuple[str, dict]], exp: Experiment) -> dict:
    """The sweep's ``table.md``, ``metrics.json`` and ``timings.json`` from ``rows``
    ((label, figures) in sweep order, the runs finished so far); returns the combined
    figures (``name@label``)."""
    combined = {f"{k}@{label}": v for label, m in rows for k, v in m.items()}
    accuracy_rows = [(label, split_timings(m, exp.timings)[0]) for label, m in rows]
    keys = sorted({k for _, m in accuracy_rows for k in m})
    table = ["| run | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    table += [
        "| " + label + " | " + " | ".join(f"{m.get(k, float('nan')):.4g}" for k in keys) + " |"
        for label, m in accuracy_rows
    ]
    out.mkdir(parents=True, exist_ok=True)
    accuracy, timing = split_timings(combined, exp.timings)
    _write_atomic(out / "table.md", ("\n".join(table) + "\n").encode())
    _write_atomic(out / "metrics.json", _json(accuracy).encode())
    if timing:
        _write_atomic(out / "timings.json", _json(timing).encode())
    return combined


def _resources(cfg: ExperimentConfig, cpus_per_task: int) -> tuple[int, int]:
    """(CPUs, GPUs) one run of ``cfg`` asks a cluster for: the GPUs its schema declares
    (:meth:`ExperimentConfig.gpus`)."""
    return cpus_per_task, cfg.gpus()


def run_config(
    path: str | Path,
    overrides: dict | None = None,
    backend: Backend | None = None,
    force: bool = False,
    cpus_per_task: int = 1,
) -> dict[str, float]:
    """Run a config file (with overrides, see :func:`experiments.config.load_config`);
    returns the flat figures written to ``metrics.json`` and ``timings.json`` together.

    ``backend`` runs the runs (default :class:`~experiments.backends.SequentialBackend`:
    one after another in this process); each sweep entry is one task asking for
    ``cpus_per_task`` CPUs (and a GPU for ``device=cuda``). A run whose folder already holds
    a complete record of the same resolved config is not run again (its figures are read
    back) unless ``force``. A sweep's combined files are rewritten after every run that
    finishes. Raises :class:`SweepFailed` when some runs failed (after the others finished).
    When no run finished and each raised an exception -- a config without a sweep, or an
    override that every run refuses -- the first run's exception is raised instead, as
    before (bad input stays a ``ValueError``: one line and status 2 on the command line).
    """
    if cpus_per_task < 1:
        raise ValueError(f"cpus_per_task must be >= 1; got {cpus_per_task}")
    name, cfg, sweep = load_config(path, {k: v.schema for k, v in EXPERIMENTS.items()}, overrides)
    exp = EXPERIMENTS[name]
    out = Path(cfg.out_dir)
    # (label, resolved config, record folder), in sweep order; a config without a sweep is
    # one run recorded in out_dir itself
    runs = [
        (label, apply_overrides(cfg, entry, where=f"sweep {label}"), out / _dir_name(label))
        for entry in sweep
        for label in [sweep_label(entry)]
    ] or [(sweep_label({}), cfg, out)]
    backend = backend or SequentialBackend()
    start = time.perf_counter()
    note(f"{name}: {path} -> {out}" + (f" ({len(sweep)} runs, {backend.name})" if sweep else ""))
    results: dict[int, dict] = {}
    for i, (_, sub, folder) in enumerate(runs):
        found = None if force else existing_record(folder, name, sub)
        if found is not None:
            results[i] = found
    if results:
        what = ", ".join(runs[i][0] for i in sorted(results)) if sweep else str(out)
        note(
            f"{name}: {len(results)} of {len(runs)} runs already recorded with the same "
            f"config, not rerun (--force reruns them): {what}"
        )
    tasks = []
    for i, (label, sub, folder) in enumerate(runs):
        if i in results:
            continue
        title = f"{name} ({folder.name})"
        cpus, gpus = _resources(sub, cpus_per_task)
        request = RunRequest(name, exp, sub, label if sweep else None, title)
        tasks.append(Task(i, label, request, cpus, gpus))
    if not sweep:
        return _run_one(name, runs[0], tasks, results, backend, start)
    failures: list[tuple[int, str, Failure]] = []
    skipped: list[tuple[int, str, str]] = []
    combined: dict[str, float] = {}
    if results:
        combined = _write_combined(out, [(runs[i][0], results[i]) for i in sorted(results)], exp)
    if tasks:
        with (
            backend,
            Tally(
                f"{name}: sweep",
                len(runs),
                done=len(results),
                running=min(len(tasks), backend.slots(tasks[0])),
            ) as tally,
        ):
            left = len(tasks)
            for outcome in backend.run(tasks, execute):
                left -= 1
                i, label = outcome.task.index, outcome.task.label
                failure = outcome.failure
                if failure is None:
                    write_record(runs[i][2], outcome.result)
                    results[i] = outcome.result.metrics
                    message = f"{label}: done in {outcome.seconds:.1f} s"
                    combined = _write_combined(
                        out, [(runs[j][0], results[j]) for j in sorted(results)], exp
                    )
                elif isinstance(failure.exception, ExperimentSkipped):
                    skipped.append((i, label, str(failure.exception)))
                    message = f"{label}: skipped: {failure.exception}"
                else:
                    failures.append((i, label, failure))
                    message = f"{label}: FAILED: {failure.summary}"
                tally.update(
                    min(left, backend.slots(outcome.task)),
                    len(results) + len(skipped),
                    len(failures),
                    message,
                )
    note(f"{name}: done in {time.perf_counter() - start:.1f} s")
    if failures:
        failures.sort()
        if not results and not skipped and all(f.exception is not None for *_, f in failures):
            # nothing ran: the error is the config's (e.g. an override every run refuses),
            # reported as for a config without a sweep; each run's line is on stdout above
            raise failures[0][2].exception
        listed = "; ".join(f"{label} ({f.summary})" for _, label, f in failures)
        kept = f"; the other runs' records are in {out}" if results else ""
        raise SweepFailed(
            f"{name}: {len(failures)} of {len(runs)} runs failed: {listed}{kept}",
            [(label, f) for _, label, f in failures],
            combined,
        )
    if skipped and not results:
        raise ExperimentSkipped(skipped[0][2])
    return combined


def _run_one(name: str, run, tasks: list[Task], results: dict, backend: Backend, start: float):
    """A config without a sweep: one run recorded in ``out_dir`` (or read back from it)."""
    label, _, out = run
    if not tasks:
        return results[0]
    with backend:
        (outcome,) = backend.run(tasks, execute)
    if outcome.failure is not None:
        if outcome.failure.exception is not None:
            raise outcome.failure.exception
        raise SweepFailed(
            f"{name}: the run failed: {outcome.failure.summary}",
            [(label, outcome.failure)],
            {},
        )
    write_record(out, outcome.result)
    note(f"{name}: done in {time.perf_counter() - start:.1f} s")
    return outcome.result.metrics
