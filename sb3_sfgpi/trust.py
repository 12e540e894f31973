"""What a run directory from elsewhere may make this machine do: allow-lists for the arguments read from ``run.json``.

A run directory is untrusted input, as a shared model is. Its ``run.json`` names the env and learner arguments that
``evaluate``, ``compare``, ``plot`` and ``--resume`` rebuild the run with; only those on an allow-list are taken (never
a deny-list): for the learners :data:`LEARNER_ARGUMENTS` (none writes files or names code), for the env the arguments
the domain declares safe to take from a run file (its ``run_file_env_kwargs``; by default those its preset sets).
Arguments that make a simulator write files or run programs (SUMO's ``sumo_args``, additional files, the GUI) are
never on it; their values, where allowed, are then checked by the learner and the env themselves.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

from sb3_sfgpi.run_settings import GAMMA

#: SFDQN arguments a run file may set (not ``tensorboard_log``, which writes files, nor classes or seeds).
LEARNER_ARGUMENTS = frozenset(
    {
        "learning_rate",
        "buffer_size",
        "learning_starts",
        "batch_size",
        "tau",
        "gamma",
        "train_freq",
        "gradient_steps",
        "optimize_memory_usage",
        "target_update_interval",
        "exploration_fraction",
        "exploration_initial_eps",
        "exploration_final_eps",
        "exploration_steps",
        "max_grad_norm",
        "planning_sweeps",
        "planning_interval",
        "optimistic_init",
        "stats_window_size",
        "policy_kwargs",
        "device",
        "replay_buffer_class",
        "replay_buffer_kwargs",
    }
)
#: The replay buffers a run file may name (those :data:`~sb3_sfgpi.common.prioritized_buffer.REPLAY_BUFFERS` resolves;
#: named here without importing torch: the commands that only read runs do not).
REPLAY_BUFFER_NAMES = ("MOReplayBuffer", "PrioritizedMOReplayBuffer")
#: Replay buffer arguments a run file may set (the prioritised buffer's, numbers).
REPLAY_BUFFER_ARGUMENTS = frozenset({"alpha", "min_priority"})
#: Policy arguments a run file may set (``net_arch``: a list of layer widths; ``n_heads`` and ``member_average``: a
#: conditioned network's).
POLICY_ARGUMENTS = frozenset({"net_arch", "n_heads", "member_average"})
_MAX_WIDTH = 1 << 16
#: A conditioned network's counts a run file may set, each with its least (also its default) and largest value.
_POLICY_COUNTS = {"n_heads": (1, 16)}


def check_learner_kwargs(kwargs: Mapping[str, Any], source: str) -> None:
    """
    Refuse learner arguments of a run file that are not on :data:`LEARNER_ARGUMENTS` (or, in ``policy_kwargs``, on
    :data:`POLICY_ARGUMENTS`, ``net_arch`` a short list of positive widths, ``n_heads`` a small positive count).

    :param source: the file, named in the error
    :raises ValueError: naming the argument
    """
    refuse_unlisted(kwargs, LEARNER_ARGUMENTS, f"{source}: learner argument", "the learners")
    gamma = kwargs.get("gamma", GAMMA)  # read as it is by evaluate and compare
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not 0.0 <= gamma <= 1.0:
        raise ValueError(f"{source}: learner argument 'gamma' must be a number in [0, 1], got {gamma!r}")
    policy_kwargs = kwargs.get("policy_kwargs", {})
    if not isinstance(policy_kwargs, dict):
        raise ValueError(f"{source}: learner argument 'policy_kwargs' must be an object, got {policy_kwargs!r}")
    refuse_unlisted(policy_kwargs, POLICY_ARGUMENTS, f"{source}: policy argument", "the networks")
    net_arch = policy_kwargs.get("net_arch", [])
    if not (
        isinstance(net_arch, list)
        and len(net_arch) <= 16
        and all(isinstance(n, int) and not isinstance(n, bool) and 0 < n <= _MAX_WIDTH for n in net_arch)
    ):
        raise ValueError(f"{source}: 'net_arch' must be a list of at most 16 widths in [1, {_MAX_WIDTH}]")
    _check_replay_buffer(kwargs, source)
    for name, (low, high) in _POLICY_COUNTS.items():
        count = policy_kwargs.get(name, low)
        if isinstance(count, bool) or not isinstance(count, int) or not low <= count <= high:
            raise ValueError(f"{source}: {name!r} must be an integer in [{low}, {high}], got {count!r}")
    average = policy_kwargs.get("member_average", 0.0)
    if isinstance(average, bool) or not isinstance(average, (int, float)) or not 0.0 <= average < 1.0:
        raise ValueError(f"{source}: 'member_average' must be a number in [0, 1), got {average!r}")


def _check_replay_buffer(kwargs: Mapping[str, Any], source: str) -> None:
    """A replay buffer named among those a learner takes by name, its arguments numbers on the allow-list."""
    name = kwargs.get("replay_buffer_class", "MOReplayBuffer")
    if name not in REPLAY_BUFFER_NAMES:
        raise ValueError(
            f"{source}: 'replay_buffer_class' must be one of {', '.join(REPLAY_BUFFER_NAMES)}, got {name!r}"
        )
    buffer_kwargs = kwargs.get("replay_buffer_kwargs", {})
    if not isinstance(buffer_kwargs, dict):
        raise ValueError(f"{source}: 'replay_buffer_kwargs' must be an object, got {buffer_kwargs!r}")
    refuse_unlisted(buffer_kwargs, REPLAY_BUFFER_ARGUMENTS, f"{source}: replay buffer argument", "the replay buffer")
    for key, value in buffer_kwargs.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{source}: replay buffer argument {key!r} must be a number, got {value!r}")


def refuse_unlisted(kwargs: Mapping[str, Any], allowed: Collection[str], what: str, whose: str) -> None:
    """
    Refuse any key of ``kwargs`` not in ``allowed``.

    :raises ValueError: "``what`` 'key' is not taken from a run file (... may set: ...)"
    """
    for key in kwargs:
        if key not in allowed:
            raise ValueError(
                f"{what} {key!r} is not taken from a run file (what a run file may set for {whose}: "
                f"{', '.join(sorted(allowed)) or 'nothing'})"
            )
