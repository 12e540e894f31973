"""The checks of SFDQN's options: values SB3 would take silently and fail on later are refused when it is built."""

from __future__ import annotations

import contextlib
import math
import numbers
from collections.abc import Mapping
from typing import Any

from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import Schedule
from stable_baselines3.common.utils import LinearSchedule

from sb3_sfgpi.common.buffers import MOReplayBuffer
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy


def learning_rate_schedule(learning_rate: float | str | Schedule) -> float | str | Schedule:
    """
    ``"lin_X"`` (RL Zoo's notation, as a JSON setting can write it) as the schedule falling linearly from ``X`` at the
    start of :meth:`SFDQN.learn` to 0 at its end; anything else as given (a malformed string too: the option check
    refuses it).
    """
    if isinstance(learning_rate, str) and learning_rate.startswith("lin_"):
        with contextlib.suppress(ValueError):
            start = float(learning_rate.removeprefix("lin_"))
            if math.isfinite(start) and start >= 0:
                return LinearSchedule(start, 0.0, 1.0)
    return learning_rate


#: The prefix of an optimism relative to the reward scale: ``"rmax_X"`` is ``X`` times the largest one-step reward.
RELATIVE_OPTIMISM = "rmax_"


def optimism_factor(optimistic_init: Any) -> float | None:
    """The factor ``X`` of ``"rmax_X"`` (a finite ``X >= 0``), None for anything else."""
    if isinstance(optimistic_init, str) and optimistic_init.startswith(RELATIVE_OPTIMISM):
        with contextlib.suppress(ValueError):
            factor = float(optimistic_init.removeprefix(RELATIVE_OPTIMISM))
            if math.isfinite(factor) and factor >= 0:
                return factor
    return None


def optimistic_value(optimistic_init: float | str, reward_low: Any, reward_high: Any) -> float:
    """
    The initial value of every table entry: ``optimistic_init`` itself, or for ``"rmax_X"`` ``X`` times the largest
    magnitude of the reward space's bounds (the largest reward one step can give), so that the same setting
    explores alike whatever the scale of the env's rewards.

    :raises ValueError: ``"rmax_X"`` with a reward space whose bounds are not finite
    """
    factor = optimism_factor(optimistic_init)
    if factor is None:
        return float(optimistic_init)
    bounds = [abs(float(bound)) for bound in (*reward_low, *reward_high)]
    if not all(math.isfinite(bound) for bound in bounds):
        raise ValueError(
            f"optimistic_init={optimistic_init!r} needs a reward_space with finite bounds, got {reward_low}, "
            f"{reward_high}: give an absolute value instead"
        )
    return factor * max(bounds)


def check_options(
    learning_rate: float | str | Schedule,
    gamma: float,
    batch_size: int,
    n_steps: int,
    replay_buffer_class: type[ReplayBuffer] | None,
) -> None:
    """Refuse out-of-range learning options and SB3 options SFDQN does not support."""
    rate_ok = isinstance(learning_rate, numbers.Real) and math.isfinite(learning_rate) and learning_rate >= 0
    if not (rate_ok or callable(learning_rate)) or isinstance(learning_rate, bool):
        raise ValueError(f"learning_rate must be a number >= 0 or a schedule ('lin_X', X >= 0), got {learning_rate!r}")
    if not isinstance(gamma, numbers.Real) or not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must be a number in [0, 1], got {gamma!r}")
    if isinstance(batch_size, bool) or not isinstance(batch_size, numbers.Integral) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    if n_steps != 1:
        raise ValueError(f"SFDQN supports only 1-step returns (n_steps=1), got n_steps={n_steps}")
    if replay_buffer_class is not None and not issubclass(replay_buffer_class, MOReplayBuffer):
        raise ValueError(
            f"replay_buffer_class must be a subclass of MOReplayBuffer (vector rewards), got {replay_buffer_class}"
        )


def check_planning_options(
    planning_sweeps: int, planning_interval: int, optimistic_init: float | str, policy_class: type
) -> None:
    """Refuse bad planning or optimism options, and planning with a policy that has no table to plan on."""
    if not isinstance(planning_sweeps, int) or planning_sweeps < 0:
        raise ValueError(f"planning_sweeps must be an integer >= 0, got {planning_sweeps!r}")
    if not isinstance(planning_interval, int) or planning_interval < 1:
        raise ValueError(f"planning_interval must be an integer >= 1, got {planning_interval!r}")
    if planning_sweeps and not issubclass(policy_class, TabularPolicy):
        raise ValueError(f"planning (planning_sweeps > 0) needs TabularPolicy, got {policy_class.__name__}")
    absolute = isinstance(optimistic_init, numbers.Real) and not isinstance(optimistic_init, bool)
    if not (absolute and math.isfinite(optimistic_init)) and optimism_factor(optimistic_init) is None:
        raise ValueError(
            f"optimistic_init must be a finite number or 'rmax_X' (X >= 0 times the largest reward), "
            f"got {optimistic_init!r}"
        )
    if optimistic_init and not planning_sweeps:
        raise ValueError("optimistic_init needs planning (planning_sweeps > 0): planning settles the optimism")


def check_schedule_options(
    buffer_size: Any,
    learning_starts: Any,
    train_freq: Any,
    gradient_steps: Any,
    target_update_interval: Any,
    tau: Any,
    exploration: tuple[Any, Any, Any],
    max_grad_norm: Any,
) -> None:
    """Refuse sizes, intervals and fractions SB3 takes silently and then divides by, or never learns with."""

    def integer(value: Any, least: int) -> bool:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= least

    def fraction(value: Any, low: float = 0.0) -> bool:
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
        return ok and low <= value <= 1.0

    frequency = train_freq[0] if isinstance(train_freq, (tuple, list)) and len(train_freq) == 2 else train_freq
    unit_ok = not isinstance(train_freq, (tuple, list)) or (
        len(train_freq) == 2 and train_freq[1] in ("step", "episode")
    )
    problems = [
        (integer(buffer_size, 1), "buffer_size must be a positive integer", buffer_size),
        (integer(learning_starts, 0), "learning_starts must be an integer >= 0", learning_starts),
        (integer(frequency, 1) and unit_ok, "train_freq must be a positive integer or (n, 'step'|'episode')",
         train_freq),
        (integer(gradient_steps, 1) or gradient_steps == -1, "gradient_steps must be a positive integer or -1",
         gradient_steps),
        (integer(target_update_interval, 1), "target_update_interval must be a positive integer",
         target_update_interval),
        (fraction(tau), "tau must be a number in [0, 1]", tau),
        (fraction(exploration[0]) and exploration[0] > 0, "exploration_fraction must be a number in (0, 1]",
         exploration[0]),
        (fraction(exploration[1]), "exploration_initial_eps must be a number in [0, 1]", exploration[1]),
        (fraction(exploration[2]), "exploration_final_eps must be a number in [0, 1]", exploration[2]),
        (isinstance(max_grad_norm, numbers.Real) and not isinstance(max_grad_norm, bool) and max_grad_norm > 0,
         "max_grad_norm must be a positive number", max_grad_norm),
    ]  # fmt: skip
    for ok, message, value in problems:
        if not ok:
            raise ValueError(f"{message}, got {value!r}")


def check_arguments(arguments: Mapping[str, Any], policy_class: type) -> None:
    """
    Refuse SFDQN's out-of-range or unsupported arguments, each named in one line.

    :param arguments: the constructor's arguments by name (the learning rate as a schedule already)
    :param policy_class: the policy class they are for
    """
    a = arguments
    check_options(a["learning_rate"], a["gamma"], a["batch_size"], a["n_steps"], a["replay_buffer_class"])
    check_planning_options(a["planning_sweeps"], a["planning_interval"], a["optimistic_init"], policy_class)
    exploration = (a["exploration_fraction"], a["exploration_initial_eps"], a["exploration_final_eps"])
    check_schedule_options(
        a["buffer_size"], a["learning_starts"], a["train_freq"], a["gradient_steps"], a["target_update_interval"],
        a["tau"], exploration, a["max_grad_norm"],
    )  # fmt: skip
    steps = a["exploration_steps"]
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, numbers.Real) or steps < 1):
        raise ValueError(f"exploration_steps must be a positive number of steps or None, got {steps!r}")
