"""Running the benchmark's task graph: one task per process call, resumable, failures recorded.

:func:`execute` runs one task (simulate a dataset, fit its field, reconstruct a cell, fine-tune
a cell) and never raises: it returns an outcome dict ``{"status": "ok" | "skipped" | "failed",
"error": str | None, "runtime_s": float, "cd": float | None}`` (a cell's outcome also holds
``"cd_visible"``, None without a visible reference). Work already done is skipped:
a dataset whose ``dataset.json`` exists (its ``phantom.json`` must hold the same settings), a
field marked ``done`` (as :func:`ultron.pipeline.field_cache.get_or_fit_field` marks it) whose
``field.json`` holds the same training settings, a cell whose ``run.json`` exists (written
last by ``reconstruct`` and ``finetune``, after the mesh, network and metrics). A
failure's traceback goes to ``error.log`` in the task's output directory.

:func:`run_tasks` runs a graph: in this process with ``jobs == 1``, otherwise in a
``ProcessPoolExecutor`` of ``jobs`` spawned workers, each on ``threads`` torch threads. A task
whose dependency failed is not run and fails with the reason.
"""

from __future__ import annotations

import json
import os
import shutil
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

from ultron import atomic
from ultron.benchmark.plan import (
    AutoLabelJob,
    FieldJob,
    FinetuneJob,
    ReconstructJob,
    SimulateJob,
    Task,
)
from ultron.benchmark.ray_executor import check_executor, run_graph_on_ray
from ultron.data.auto_label_dataset import auto_label_dataset, auto_label_records
from ultron.data.dataset import SweepDataset
from ultron.errors import UltronInputError
from ultron.methods.finetune import FinetuneConfig
from ultron.models.field_dir import (
    CHECKPOINT,
    FIELD_JSON,
    FIT_DONE,
    TRANSMISSION_CHECK,
    read_field_json,
)
from ultron.models.fitted import load_field
from ultron.parallel import available_cores
from ultron.phantom.dataset import simulate_dataset
from ultron.pipeline.finetune import finetune
from ultron.pipeline.record import RunRecord
from ultron.pipeline.run import reconstruct
from ultron.train.field_fit import fit_field
from ultron.train.fit_shape import resolve_fit_shape
from ultron.train.transmission_check import record_transmission_check

Outcome = dict[str, Any]
#: Called with (task, outcome, tasks finished, tasks in total) as each task ends.
Report = Callable[[Task, Outcome, int, int], None]


def default_threads(jobs: int) -> int:
    """torch threads per task: the machine's cores shared among ``jobs`` workers, ≥ 1."""
    return max(1, available_cores() // max(1, jobs))


def _normalised(data: Any) -> Any:
    return json.loads(json.dumps(data, default=str))


def _previous_runtime(out: Path) -> float:
    """The finished cell's recorded seconds (0 when its run.json is unreadable)."""
    try:
        return RunRecord.read(out).total_s
    except UltronInputError:
        return 0.0


def _cell_cds(out: Path) -> dict[str, float | None]:
    """``cd`` and ``cd_visible`` means of ``out/metrics.json``, read once (each None when
    missing, unreadable or null)."""
    try:
        means = json.loads((out / "metrics.json").read_text(encoding="utf-8"))["mean"]
    except (OSError, ValueError, KeyError, TypeError):
        means = {}
    result: dict[str, float | None] = {}
    for name in ("cd", "cd_visible"):
        try:
            result[name] = float(means[name])
        except (KeyError, TypeError, ValueError):
            result[name] = None
    return result


def simulate(job: SimulateJob) -> bool:
    """Simulate the dataset unless it exists; True when skipped."""
    out = Path(job.out)
    if (out / "dataset.json").is_file():
        saved = out / "phantom.json"
        try:
            previous = json.loads(saved.read_text(encoding="utf-8")).get("config")
        except (OSError, ValueError) as exc:
            raise UltronInputError(saved, "config", f"cannot be read ({exc})") from None
        if _normalised(previous) != _normalised(job.config.to_dict()):
            raise UltronInputError(
                saved, "config", "simulated with other settings; use another --out directory"
            )
        return True
    simulate_dataset(job.config, out=out)
    return False


def fit(job: FieldJob) -> bool:
    """Fit the dataset's field unless it is done with the same settings; True when skipped."""
    out = Path(job.out)
    dataset = SweepDataset.load(job.dataset_dir)
    config = resolve_fit_shape(job.config, dataset)  # field.json records the resolved shape
    done = all((out / name).is_file() for name in (FIT_DONE, FIELD_JSON, CHECKPOINT))
    if done and _normalised(read_field_json(out).get("train")) == _normalised(config.to_dict()):
        if not (out / TRANSMISSION_CHECK).is_file():  # fitted before the check was written
            record_transmission_check(dataset, load_field(out, job.device), out)
        return True
    # resumes a checkpoint (also a larger iteration count); other settings are an error
    fit_field(dataset, config, out, resume=True, device=job.device)  # writes FIT_DONE last
    return False


def auto_label(job: AutoLabelJob) -> bool:
    """Write the dataset's auto-labelled copy unless it exists with the same settings; True
    when skipped. The copy is labelled in a hidden sibling and renamed into place, so a
    killed task leaves no half-labelled dataset."""
    out = Path(job.out)
    if (out / "dataset.json").is_file():
        dataset = SweepDataset.load(out)
        records = auto_label_records(dataset)
        wanted = _normalised(job.config.to_dict())
        if len(records) == len(dataset.sweeps) and all(
            _normalised(r.get("config")) == wanted for r in records.values()
        ):
            return True
        raise UltronInputError(
            out / "dataset.json",
            "metadata.auto_labels",
            "labelled with other settings; use another --out directory",
        )
    staging = out.with_name(f".{out.name}.new")
    shutil.rmtree(staging, ignore_errors=True)
    shutil.copytree(job.dataset_dir, staging)
    auto_label_dataset(staging, None, replace=True, config=job.config)
    os.replace(staging, out)
    return False


def _cell_done(out: str | Path) -> bool:
    """Whether a cell's run.json exists; if not, an earlier failure's ``error.log`` (the only
    file a failed cell leaves: a run replaces its directory as a whole, see
    :mod:`ultron.pipeline.rundir`) is removed so that the run may take the directory."""
    if (Path(out) / "run.json").is_file():
        return True
    (Path(out) / "error.log").unlink(missing_ok=True)
    return False


def reconstruct_cell(job: ReconstructJob) -> bool:
    """One ``reconstruct`` cell unless its run.json exists; True when skipped."""
    if _cell_done(job.out):
        return True
    reconstruct(
        job.dataset_dir,
        job.request,
        job.out,
        field_dir=job.field_dir,
        allow_other_field=job.allow_other_field,
        report=job.report,
    )
    return False


def finetune_cell(job: FinetuneJob) -> bool:
    """One Table 2 fine-tuning cell unless its run.json exists; True when skipped."""
    if _cell_done(job.out):
        return True

    config = FinetuneConfig(
        label_fraction=job.label_fraction,
        iters=job.iters,
        seed=job.seed,
        meshing=job.meshing,  # the benchmark's meshing and metrics
        metrics=job.metrics,
        device=job.device,
    )
    finetune(
        job.model_dir, job.dataset_dir, config, job.out, field_dir=job.field_dir, report=job.report
    )
    return False


_HANDLERS: dict[type, Callable[[Any], bool]] = {
    SimulateJob: simulate,
    FieldJob: fit,
    AutoLabelJob: auto_label,
    ReconstructJob: reconstruct_cell,
    FinetuneJob: finetune_cell,
}


def execute(task: Task) -> Outcome:
    """Run ``task`` (see the module doc); never raises."""
    start = time.perf_counter()
    out = Path(task.job.out)
    try:
        skipped = _HANDLERS[type(task.job)](task.job)
    except Exception as exc:
        message = f"{type(exc).__name__}: {exc}"
        try:
            atomic.write_text(out / "error.log", traceback.format_exc())
        except OSError:
            pass
        return {"status": "failed", "error": message, "runtime_s": _elapsed(start), "cd": None}
    (out / "error.log").unlink(missing_ok=True)
    runtime = _previous_runtime(out) if skipped and task.is_cell else _elapsed(start)
    return {
        "status": "skipped" if skipped else "ok",
        "error": None,
        "runtime_s": runtime,
        **(_cell_cds(out) if task.is_cell else {"cd": None, "cd_visible": None}),
    }


def _elapsed(start: float) -> float:
    return round(time.perf_counter() - start, 3)


def _init_worker(threads: int) -> None:
    import torch

    torch.set_num_threads(threads)


def _blocked(task: Task, outcomes: Mapping[str, Outcome]) -> Outcome | None:
    """The failed outcome of a task whose dependency failed, else None."""
    for dep in task.deps:
        if outcomes[dep]["status"] == "failed":
            reason = outcomes[dep]["error"] or "failed"
            if reason.startswith("not run: "):
                reason = reason.removeprefix("not run: ")
            else:
                reason = f"{dep} failed ({reason})"
            return {"status": "failed", "error": f"not run: {reason}", "runtime_s": 0.0, "cd": None}
    return None


class _Graph:
    """Pending tasks and outcomes: hands out tasks whose dependencies have finished."""

    def __init__(self, tasks: Sequence[Task], report: Report | None) -> None:
        self.total, self.report = len(tasks), report
        self.pending = list(tasks)
        self.outcomes: dict[str, Outcome] = {}

    def finish(self, task: Task, outcome: Outcome) -> None:
        self.outcomes[task.id] = outcome
        if self.report is not None:
            self.report(task, outcome, len(self.outcomes), self.total)

    def take_ready(self) -> list[Task]:
        """Tasks now runnable; those blocked by a failed dependency are finished as failed."""
        runnable: list[Task] = []
        blocked_any = True
        while blocked_any:  # a blocked task may unblock (as failed) the tasks after it
            blocked_any = False
            ready = [t for t in self.pending if all(d in self.outcomes for d in t.deps)]
            for task in ready:
                self.pending.remove(task)
                blocked = _blocked(task, self.outcomes)
                if blocked is None:
                    runnable.append(task)
                else:
                    self.finish(task, blocked)
                    blocked_any = True
        return runnable


def run_tasks(
    tasks: Sequence[Task],
    jobs: int = 1,
    threads: int | None = None,
    report: Report | None = None,
    worker: Callable[[Task], Outcome] = execute,
    executor: str = "local",
    address: str | None = None,
    gpus: float = 0.0,
) -> dict[str, Outcome]:
    """Run every task after its dependencies (module doc); outcomes by task id.

    ``worker`` (a module-level function, picklable for the pool) runs one task. ``executor``
    ``"local"`` runs ``jobs`` tasks at a time on this machine; ``"ray"`` runs them as Ray tasks
    of ``threads`` CPUs and ``gpus`` GPUs each (:mod:`ultron.benchmark.ray_executor`;
    ``address``: a Ray cluster to join, default a local one).
    """
    check_executor(executor, address)
    ids = {t.id for t in tasks}
    for task in tasks:
        unknown = [d for d in task.deps if d not in ids]
        if unknown:
            raise UltronInputError("argument", "tasks", f"{task.id} depends on unknown {unknown}")
    graph = _Graph(tasks, report)
    threads = threads or default_threads(jobs)
    if executor == "ray":
        run_graph_on_ray(graph, threads, worker, address, _crash, gpus)
    elif jobs == 1:
        _run_serial(graph, threads, worker)
    else:
        _run_pool(graph, jobs, threads, worker)
    for task in list(graph.pending):  # only reachable with a dependency cycle
        graph.finish(task, {"status": "failed", "error": "dependency cycle", "runtime_s": 0.0})
    return graph.outcomes


def _run_serial(graph: _Graph, threads: int, worker: Callable[[Task], Outcome]) -> None:
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    order = {task.id: i for i, task in enumerate(graph.pending)}
    queue: list[Task] = []
    try:  # always the earliest runnable task of the plan: a dataset's cells before the next's
        while queue := sorted(queue + graph.take_ready(), key=lambda t: order[t.id]):
            task = queue.pop(0)
            graph.finish(task, worker(task))
    finally:
        torch.set_num_threads(previous)


def _run_pool(graph: _Graph, jobs: int, threads: int, worker: Callable[[Task], Outcome]) -> None:
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    running: dict[Future, Task] = {}
    with ProcessPoolExecutor(
        max_workers=jobs, mp_context=context, initializer=_init_worker, initargs=(threads,)
    ) as pool:

        def submit_ready() -> None:
            while ready := graph.take_ready():
                for task in ready:
                    try:
                        running[pool.submit(worker, task)] = task
                    except Exception as exc:  # e.g. a broken pool after a worker died
                        graph.finish(task, _crash(exc))
                if running:
                    return

        submit_ready()
        while running:
            done, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for future in done:
                task = running.pop(future)
                try:
                    outcome = future.result()
                except Exception as exc:  # the worker process died (e.g. out of memory)
                    outcome = _crash(exc)
                graph.finish(task, outcome)
            submit_ready()


def _crash(exc: BaseException) -> Outcome:
    message = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return {"status": "failed", "error": message, "runtime_s": 0.0, "cd": None}
