"""The method settings of a run and the values they may take: plain data that imports nothing.

The learners, schedules and callbacks check their arguments against these (and re-export them where they were
defined before); the command line checks a preset's or ``--set``'s values with them without importing torch or
Stable-Baselines3.
"""

from __future__ import annotations

#: The name of the one learner all agents share (``sharing="shared"``).
#: The discount factor of learners, runs and evaluations that are given none.
GAMMA = 0.99
SHARED = "shared"
#: How agents get their learners: one each, or one for all (:class:`~sb3_sfgpi.multiagent.MultiAgentRunner`'s
#: ``sharing``).
SHARINGS = ("independent", SHARED)
#: The ways :class:`~sb3_sfgpi.schedules.OLSSchedule` takes a round's weights from the queue.
OLS_BATCHES = ("top", "same-after-extrema")
#: How the values of new policies can be estimated (see :class:`~sb3_sfgpi.callbacks.ValueEstimation`).
VALUE_MODES = ("joint", "shared")

#: The settings stored in ``run.json`` (what :meth:`MASFOLS.load <sb3_sfgpi.masfols.MASFOLS.load>` rebuilds a run
#: from).
SETTINGS = (
    "policy",
    "weights",
    "ols_batch",
    "steps_per_iteration",
    "learner_kwargs",
    "test_weights",
    "seed",
    "value_mode",
    "value_episodes",
    "eval_episodes",
    "gpi_set",
    "validation_weights",
    "prune",
    "admit_together",
    "sharing",
    "n_envs",
    "pool_replay",
)


def acts_by_own_policies(fixed: bool, sharing: str) -> bool:
    """
    Whether each agent of a run is evaluated by GPI over the policies it learned itself: fixed weights (a priori
    scalarised learners) with one learner per agent. Otherwise every agent acts by GPI over the whole set.
    """
    return fixed and sharing != SHARED
