"""morl-baselines' GPI-LS trained one iteration at a time, so that a peer's run of hours survives an interruption.

``GPIPD.train(..., weight_selection_algo="gpi-ls")`` runs all its iterations in one call and keeps nothing between
them. :func:`train_gpi_ls` runs the same iterations by the same public steps of the agent and of its
``LinearSupport`` (the next weight by GPI-LS's priority over the support, an iteration of training over the support,
its top-4 corner weights and the new weight, then each of those weights' GPI value added to the support), without
wandb and checkpoint files, and, given a path, saves the whole run after every iteration: the agent with its replay
buffer and optimisers, the support, the evaluation env and the global generators. A run found at the path goes on
from there to the same end as a run straight through.

The checkpoint is morl-baselines' own objects, pickled as they are (:class:`_Snapshot`): only ever read from a
directory the benchmark itself wrote (``--runs``), never from elsewhere.
"""

from __future__ import annotations

import io
import pickle
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import torch as th
from gymnasium.utils import EzPickle

#: Episodes per weight of GPI-LS's own policy evaluations (its ``train``'s default).
EVALUATION_EPISODES = 5
#: Corner weights trained beside the support each iteration (its ``train``'s).
TOP_CORNERS = 4


@dataclass
class GpiLsRun:
    """A GPI-LS run between two iterations: all its ``train`` loop carries from one to the next."""

    agent: Any
    support: Any  # morl-baselines' LinearSupport
    eval_env: Any
    settings: dict[str, Any]  # what the benchmark ran it with: a stored run of other settings is refused
    iterations: int = 0  # done
    wall_time: float = 0.0  # of training and weight selection, over all sessions
    finished: bool = False  # GPI-LS found no weight to train on
    generators: tuple[Any, ...] = ()  # the global generators' states at the checkpoint


def train_gpi_ls(
    make_agent: Callable[[], Any],
    make_eval_env: Callable[[], Any],
    settings: dict[str, Any],
    steps: int,
    iterations: int,
    checkpoint: Path | None = None,
) -> GpiLsRun:
    """
    GPI-LS trained for ``iterations`` iterations of ``steps`` env steps (or until it finds no weight to train on).

    :param make_agent: a new ``GPIPD`` agent (called only where no run is stored)
    :param make_eval_env: the env its weight selection evaluates on (built after the agent, as in the peers' order)
    :param settings: the run's settings, stored with it and compared with a stored run's
    :param checkpoint: the file the run is saved to after every iteration and continued from (None: none)
    :raises ValueError: ``checkpoint`` holds a run of other settings
    """
    run = _stored(checkpoint, settings)
    if run is None:
        from morl_baselines.multi_policy.linear_support.linear_support import LinearSupport

        agent = make_agent()
        run = GpiLsRun(agent, LinearSupport(num_objectives=agent.reward_dim, epsilon=None), make_eval_env(), settings)
    while run.iterations < iterations and not run.finished:
        start = time.perf_counter()
        _iteration(run, steps)
        run.wall_time += time.perf_counter() - start
        if checkpoint is not None:
            _save(run, checkpoint)
    return run


def _iteration(run: GpiLsRun, steps: int) -> None:
    """One iteration of ``GPIPD.train``'s GPI-LS loop (its logging and checkpoint files off)."""
    from morl_baselines.common.evaluation import policy_evaluation_mo

    agent, support = run.agent, run.support
    agent.set_weight_support(support.get_weight_support())
    use_gpi, agent.use_gpi = agent.use_gpi, True
    w = support.next_weight(algo="gpi-ls", gpi_agent=agent, env=run.eval_env, rep_eval=EVALUATION_EPISODES)
    agent.use_gpi = use_gpi
    if w is None:
        run.finished = True
        return
    trained = support.get_weight_support() + support.get_corner_weights(top_k=TOP_CORNERS) + [w]
    agent.train_iteration(
        total_timesteps=steps, weight=w, weight_support=trained, change_w_every_episode=True,
        eval_env=run.eval_env, reset_num_timesteps=False, reset_learning_starts=False,
    )  # fmt: skip
    for weight in trained:
        support.add_solution(policy_evaluation_mo(agent, run.eval_env, weight, rep=EVALUATION_EPISODES)[3], weight)
    run.iterations += 1


class _Snapshot(cloudpickle.CloudPickler):
    """
    cloudpickle (morl-baselines' agents hold lambdas) that keeps the objects Gymnasium's ``EzPickle`` would rebuild
    from their constructor's arguments (MO-Gymnasium's envs) as they are: their generators and their episode's state.
    """

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, EzPickle):
            return object.__new__, (type(obj),), obj.__dict__, None, None, _restore_attributes
        return super().reducer_override(obj)


def _restore_attributes(obj: Any, attributes: dict[str, Any]) -> None:
    obj.__dict__.update(attributes)


def _save(run: GpiLsRun, checkpoint: Path) -> None:
    """The run and the global generators' states, written whole or not at all."""
    cuda = th.cuda.get_rng_state_all() if th.cuda.is_available() else []
    run.generators = (random.getstate(), np.random.get_state(), th.get_rng_state(), cuda)  # noqa: NPY002 - the peer's
    snapshot = io.BytesIO()
    _Snapshot(snapshot, protocol=pickle.HIGHEST_PROTOCOL).dump(run)
    partial = checkpoint.with_name(checkpoint.name + ".partial")
    partial.parent.mkdir(parents=True, exist_ok=True)
    partial.write_bytes(snapshot.getvalue())
    partial.replace(checkpoint)


def _stored(checkpoint: Path | None, settings: dict[str, Any]) -> GpiLsRun | None:
    """The run saved at ``checkpoint`` with the global generators as they were then, or None where there is none."""
    if checkpoint is None or not checkpoint.exists():
        return None
    run = pickle.loads(checkpoint.read_bytes())  # noqa: S301 - a file this benchmark wrote (module docstring)
    if run.settings != settings:
        raise ValueError(f"{checkpoint} holds a GPI-LS run of other settings than this benchmark's: move it away")
    python, numpy, torch, cuda = run.generators
    random.setstate(python)
    np.random.set_state(numpy)  # noqa: NPY002 - the peer's
    th.set_rng_state(torch)
    if cuda:
        th.cuda.set_rng_state_all(cuda)
    return run
