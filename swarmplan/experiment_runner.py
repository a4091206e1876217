"""The batch runner of the paper's section 4: every (algorithm, scenario, seed) of an experiment
flown offline (``sim_gateway.offline_runner.run_offline``), in parallel over local processes or
on a Dask distributed cluster, with a progress bar.

- ``efficiency`` is section 4.2: ``paper-2uav`` (two UAVs, no threats) with PSO, ACOAPF and
  HAPF-ACO.
- ``swarm`` is section 4.3: ``paper-10uav`` and ``paper-20uav`` (random starts, five threats,
  L_max = 330 km); the paper shows HAPF-ACO only, we fly all three algorithms.

Seed ``s`` fixes the world (target truth, sensor noise) and the start states, so the algorithms
of one seed meet the same mission: the seeds are the blocks of the Friedman test. A run's result
depends only on (scenario, algorithm, seed, steps), never on where or in which order it ran,
so local and Dask runs give identical results.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

from tqdm import tqdm

from planner.errors import UserError
from planner.scenario import Scenario, load_scenario
from sim_gateway.offline_runner import run_offline

#: The algorithms in the paper's order (Algorithms 1-3 of section 4.2).
ALGORITHMS = ("pso", "acoapf", "hapf-aco")


@dataclass(frozen=True)
class Experiment:
    name: str
    section: str
    scenarios: tuple[str, ...]
    description: str


EXPERIMENTS = {
    "efficiency": Experiment(
        "efficiency",
        "4.2",
        ("paper-2uav",),
        "task execution efficiency: 2 UAVs from (10,10) and (90,90) km, no threats",
    ),
    "swarm": Experiment(
        "swarm",
        "4.3",
        ("paper-10uav", "paper-20uav"),
        "obstacle and collision avoidance: 10 and 20 UAVs, random starts, 5 threats, L_max 330 km",
    ),
}


@dataclass(frozen=True)
class RunTask:
    """One run of an experiment; everything its result depends on."""

    experiment: str
    scenario: Scenario
    algorithm: str
    seed: int
    steps: int

    @property
    def key(self) -> tuple[str, str, int]:
        return (self.scenario.name, self.algorithm, self.seed)


def run_task(task: RunTask) -> dict:
    """Fly one run (in a worker process or on a Dask worker); the result dict of
    ``planner.metrics.MissionRecorder.result`` plus the experiment's name."""
    cpu = time.process_time()
    result = run_offline(task.scenario, task.seed, task.steps, task.algorithm)
    result["experiment"] = task.experiment
    result["cpu_time_s"] = time.process_time() - cpu  # this process's CPU time for the run
    return result


def plan_tasks(
    experiment: str, runs: int, seed_base: int, steps: int | None, algorithms: Sequence[str]
) -> list[RunTask]:
    """The runs of an experiment in canonical order: scenario, algorithm, seed."""
    spec = EXPERIMENTS[experiment]
    tasks = []
    for name in spec.scenarios:
        scenario = load_scenario(name)
        for algorithm in algorithms:
            for seed in range(seed_base, seed_base + runs):
                tasks.append(
                    RunTask(experiment, scenario, algorithm, seed, steps or scenario.steps)
                )
    return tasks


def _cost(task: RunTask) -> float:
    """Rough relative cost, to start the longest runs first (better load balance)."""
    return task.scenario.uav_count * task.steps


def _single_thread_env() -> None:
    """Worker processes each run one planner; keep BLAS/OpenMP from oversubscribing the cores."""
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")


def execute(
    tasks: Sequence[RunTask],
    jobs: int = 1,
    dask_address: str | None = None,
    progress: bool = True,
    on_result: Callable[[RunTask, dict], None] | None = None,
) -> dict[tuple[str, str, int], dict]:
    """Run ``tasks`` (in-process when ``jobs`` is 1, else on ``jobs`` local processes, or on the
    Dask scheduler at ``dask_address``); returns the results by task key. ``on_result`` sees each
    result as it arrives (e.g. to write it to disk)."""
    order = sorted(tasks, key=lambda t: -_cost(t))  # stable: canonical order within a cost
    results: dict[tuple[str, str, int], dict] = {}
    client = _dask_client(dask_address) if dask_address is not None else None
    with tqdm(
        total=len(tasks),
        unit="run",
        file=sys.stderr,
        disable=not progress,
        smoothing=0.05,
        desc=tasks[0].experiment if tasks else "experiment",
    ) as bar:

        def done(task: RunTask, result: dict) -> None:
            if on_result is not None:
                on_result(task, result)
            results[task.key] = result
            bar.set_postfix_str(
                f"{task.scenario.name} {task.algorithm} seed {task.seed}", refresh=False
            )
            bar.update(1)

        if client is not None:
            _execute_dask(order, client, done)
        elif jobs <= 1:
            for task in order:
                done(task, run_task(task))
        else:
            _execute_processes(order, jobs, done)
    return results


def _execute_processes(
    order: Iterable[RunTask], jobs: int, done: Callable[[RunTask, dict], None]
) -> None:
    _single_thread_env()
    methods = multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("forkserver" if "forkserver" in methods else None)
    with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        futures = {pool.submit(run_task, task): task for task in order}
        try:
            for future in as_completed(futures):
                done(futures[future], future.result())
        except BaseException:
            for future in futures:
                future.cancel()
            raise


def _dask_client(address: str):
    """A client of the Dask scheduler at ``address`` (a UserError when it cannot be reached)."""
    try:
        from distributed import Client
    except ImportError:
        raise UserError(
            "--dask needs dask.distributed; install it with pip install 'hapf-aco-swarm[dask]'"
        ) from None
    try:
        return Client(address, timeout="15s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise UserError(
            f"cannot reach the Dask scheduler at {address} ({exc.__class__.__name__}); start one "
            "with `dask scheduler` and workers with `dask worker ADDRESS`, or drop --dask"
        ) from None


def _execute_dask(order: Sequence[RunTask], client, done: Callable[[RunTask, dict], None]) -> None:
    """The same runs on the cluster's workers (which need this project installed)."""
    from distributed import as_completed as dask_completed

    try:
        futures = [client.submit(run_task, task, pure=False) for task in order]
        by_future = dict(zip(futures, order, strict=True))
        with client.as_current():
            for future in dask_completed(futures):
                done(by_future[future], future.result())
    finally:
        client.close()
