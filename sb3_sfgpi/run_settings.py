"""The method settings of a run and the values they may take: plain data that imports nothing.

The learners, schedules and callbacks check their arguments against these (and re-export them where they were
defined before); the command line checks a preset's or ``--set``'s values with them without importing torch or
Stable-Baselines3.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

#: The discount factor of learners, runs and evaluations that are given none.
GAMMA = 0.99
#: The name of the one learner all agents share (``sharing="shared"``).
SHARED = "shared"
#: How agents get their learners: one each, or one for all (:class:`~sb3_sfgpi.multiagent.MultiAgentRunner`'s
#: ``sharing``).
SHARINGS = ("independent", SHARED)
#: The ways :class:`~sb3_sfgpi.schedules.OLSSchedule` takes a round's weights from the queue.
OLS_BATCHES = ("top", "same-after-extrema")
#: How the values of new policies can be estimated (see :class:`~sb3_sfgpi.callbacks.ValueEstimation`).
VALUE_MODES = ("joint", "shared")
#: What conditioned learners act and train for in each episode (see :mod:`~sb3_sfgpi.episode_weights`).
EPISODE_WEIGHTS = ("own", "support")
#: Settings added after runs were first written: a ``run.json`` without one is of a run that had its default.
ADDED_LATER = ("episode_weights", "rebind_support")
#: Settings that runs were written with and this version no longer has, each with the value it behaves as: a run
#: stored with another value cannot be continued (``snapshots``: removed on 2026-12-02, the levers page says why).
REMOVED = {"snapshots": 0}


@dataclass(frozen=True)
class RunSettings:
    """
    The settings of a :class:`~sb3_sfgpi.masfols.MASFOLS` run that decide its results: what ``run.json`` stores and
    what :meth:`MASFOLS.from_settings <sb3_sfgpi.masfols.MASFOLS.from_settings>` builds a run from (its arguments
    of the same names say what each one is).

    ``test_weights`` is an array ``(n, d)``, a number ``n`` of Dirichlet(1) weights drawn with seed 0, or None (12
    such weights; fixed weights: those); a run stores the array it drew.
    """

    policy: str = "TabularPolicy"
    weights: str | list[float] = "ols"
    ols_batch: str = "top"
    steps_per_iteration: int = 10_000
    learner_kwargs: dict[str, Any] = field(default_factory=dict)
    test_weights: Any = None
    seed: int = 0
    value_mode: str = "joint"
    value_episodes: int = 1
    eval_episodes: int = 1
    gpi_set: str = "all"
    validation_weights: int = 0
    prune: bool = False
    admit_together: bool = False
    sharing: str = "independent"
    n_envs: int = 1
    pool_replay: bool = False
    episode_weights: str = EPISODE_WEIGHTS[0]
    rebind_support: bool = False

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The settings' names, in ``run.json``'s order."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def stored(cls, config: Mapping[str, Any], where: str) -> RunSettings:
        """
        The settings of a ``run.json`` (its other keys ignored).

        :param where: the file, for the error
        :raises ValueError: a setting is missing, or a removed one is not at the value this version behaves as
        """
        removed = {name: config[name] for name, kept in REMOVED.items() if config.get(name, kept) != kept}
        if removed:
            raise ValueError(f"{where} is of a run with {removed}, which this version no longer has: it cannot go on")
        missing = [name for name in cls.names() if name not in config and name not in ADDED_LATER]
        if missing:
            raise ValueError(f"{where} lacks the settings {missing}: not a run of MASFOLS")
        return cls(**{name: config[name] for name in cls.names() if name in config})

    def to_json(self) -> dict[str, Any]:
        """The settings as ``run.json`` stores them."""
        return asdict(self)


def acts_by_own_policies(fixed: bool, sharing: str) -> bool:
    """
    Whether each agent of a run is evaluated by GPI over the policies it learned itself: fixed weights (a priori
    scalarised learners) with one learner per agent. Otherwise every agent acts by GPI over the whole set.
    """
    return fixed and sharing != SHARED
