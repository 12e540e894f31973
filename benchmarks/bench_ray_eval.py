"""Evaluation jobs on Ray actors vs the library's pool of worker processes (issue 13: one mechanism or two?).

The same traffic evaluation jobs (episodes of SUMO's fixed-time program: the env and the rollout loop of a GPI
evaluation, without a policy to load) run on :class:`~sb3_sfgpi.evaluation_jobs.ParallelEvaluator` with 2 spawned
processes and on 2 Ray actors that hold the same worker state (each its own env), both started and warmed up
before timing, interleaved. Starting Ray itself is timed apart.
"""

from __future__ import annotations

import os
import time

from benchmarks._common import Row, fmt_time, interleaved_samples, paired_ratio

WORKERS = 2
ENV_KWARGS = {"num_seconds": 300, "signal_control": "fixed-time"}


def run(quick: bool = False) -> list[Row]:
    """Seconds per batch of evaluation jobs: Ray actors vs the process pool."""
    try:
        import ray
    except ImportError:
        return [Row("evaluation", "Ray actors vs worker processes", "skipped: ray is not installed")]
    from sfgpi_envs.traffic import TrafficSignalEnv

    from sb3_sfgpi import evaluation
    from sb3_sfgpi.evaluation_jobs import EvaluationJob, ParallelEvaluator

    @ray.remote(num_cpus=1)
    class EvaluationActor:
        """A worker of ParallelEvaluator's kind, as a Ray actor."""

        def __init__(self) -> None:
            evaluation._init_worker(TrafficSignalEnv, ENV_KWARGS, 0.95, 1, os.getppid())

        def run(self, job: EvaluationJob):
            return evaluation._run_job_in_worker(job)

    jobs = [EvaluationJob(seed) for seed in range(1000, 1000 + (4 if quick else 8))]
    start = time.perf_counter()
    ray.init(num_cpus=WORKERS, include_dashboard=False, log_to_driver=False)
    ray_start = time.perf_counter() - start
    actors = [EvaluationActor.remote() for _ in range(WORKERS)]
    pool = ParallelEvaluator(TrafficSignalEnv, ENV_KWARGS, workers=WORKERS)
    try:

        def on_ray() -> None:
            ray.get([actors[i % WORKERS].run.remote(job) for i, job in enumerate(jobs)])

        samples = interleaved_samples({"pool": lambda: pool.run(jobs), "ray": on_ray}, repeats=3 if quick else 5)
    finally:
        pool.close()
        ray.shutdown()
    ratio = paired_ratio(samples, "pool", "ray")[0]
    median = {name: sorted(values)[len(values) // 2] for name, values in samples.items()}
    return [
        Row(
            "evaluation",
            f"{len(jobs)} traffic episodes of {ENV_KWARGS['num_seconds']} s: {WORKERS} Ray actors vs {WORKERS} worker "
            "processes",
            fmt_time(median["ray"]),
            fmt_time(median["pool"]),
            ratio,
            "",
            None,
            f"both warmed up; starting Ray took {ray_start:.1f} s more",
        )
    ]
