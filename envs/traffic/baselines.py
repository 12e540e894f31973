"""Signal-control baselines without learning: SUMO's fixed-time and actuated programs, and max-pressure.

:func:`run_program_episode` runs one full episode of :class:`~.env.TrafficSignalEnv` with the lights
driven by SUMO's own program or by max-pressure (:mod:`.max_pressure`) and returns the same episode metrics as the
learning environment.
"""

from __future__ import annotations

from typing import Any

from .env import TrafficSignalEnv

PROGRAMS = ("fixed-time", "actuated", "max-pressure")
"""Baseline controllers: the static program of the network, the actuated programs, or max-pressure."""


def run_program_episode(program: str = "fixed-time", seed: int | None = None, **env_kwargs: Any) -> dict[str, float]:
    """Run one episode with SUMO's own signal program, or with max-pressure.

    :param program: ``"fixed-time"`` (the static program compiled into the network), ``"actuated"``
        (SUMO's gap-based actuated programs derived from it, :func:`~.scenario.write_actuated_programs`) or
        ``"max-pressure"`` (the green of largest vehicle pressure at every decision, :mod:`.max_pressure`).
    :param seed: SUMO seed.
    :param env_kwargs: further :class:`~.env.TrafficSignalEnv` arguments (``num_seconds``,
        ``net_file``, ``backend``, ...); ``signal_control`` is set from ``program``.
    :return: :meth:`~.env.TrafficSignalEnv.episode_metrics` at the end of the episode.
    :raises ValueError: for an unknown program.
    """
    if program not in PROGRAMS:
        raise ValueError(f"program must be one of {PROGRAMS}, got {program!r}")
    if "signal_control" in env_kwargs:
        raise ValueError("signal_control is set by `program`; do not pass it")
    env = TrafficSignalEnv(signal_control=program, seed=seed, **env_kwargs)
    try:
        env.reset(seed=seed)
        while env.agents:
            env.step({})
        return env.episode_metrics()
    finally:
        env.close()
