"""Shared fixtures: the paper's Fig. 1 MOMDP (``tests/momdp.py``), small SFDQN models and SF networks."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from momdp import Fig1MOMDP
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import FlattenExtractor

from sb3_sfgpi.sfdqn import SFDQN, SFNetwork, TabularSFNetwork

# The networks here are tiny: one thread per test process is faster, above all when pytest-xdist runs two.
th.set_num_threads(1)
# Ray starts its task workers at niceness 15: beside the other xdist process a sweep test's run then waits minutes
# for the CPU (a checkpoint 140 s late instead of 18 s). Local Rays that tests start inherit this.
os.environ.setdefault("RAY_worker_niceness", "0")

#: Settings under which tabular SFDQN solves the Fig. 1 MOMDP (γ = 1) in about a second.
FIG1_TABULAR_KWARGS: dict[str, Any] = dict(
    learning_rate=0.5,
    gamma=1.0,
    batch_size=1,
    train_freq=1,
    learning_starts=0,
    buffer_size=1_000,
    exploration_fraction=0.5,
    exploration_initial_eps=1.0,
    exploration_final_eps=0.1,
)
FIG1_TABULAR_STEPS = 1_200
#: `train` options for tests of training mechanics on the four-room preset: validating untrained policies on the
#: preset's 100 validation weights would take minutes
FEW_VALIDATION = ["--set", "validation_weights=4"]


def tiny_four_room(steps: int = 100) -> list[str]:
    """The command line of a four-room run of one iteration of ``steps`` joint steps and 2 test weights."""
    return ["train", "four-room", "--iterations", "1", "--steps-per-iteration", str(steps), "--set", "n_test_weights=2"]


def train_tiny_run(out: Path, steps: int = 100) -> Path:
    """A finished :func:`tiny_four_room` run in ``out`` (few validation weights)."""
    from sb3_sfgpi.cli import main

    assert main([*tiny_four_room(steps), *FEW_VALIDATION, "--no-progress", "--out", str(out)]) == 0
    return out


class StopAfter(BaseCallback):
    """Stops a run (as a kill would) after ``steps`` joint steps."""

    def __init__(self, steps: int):
        super().__init__()
        self.steps = steps

    def _on_step(self) -> bool:
        return self.model.num_timesteps < self.steps


BAD_WEIGHTS = [
    pytest.param([1.0], "length", id="wrong-length"),
    pytest.param([0.5, 0.3, 0.2], "length", id="too-long"),
    pytest.param([-0.5, 1.5], "non-negative", id="negative"),
    pytest.param([float("nan"), 1.0], "finite", id="nan"),
    pytest.param([0.0, 0.0], "all zero", id="all-zero"),
]


@pytest.fixture(autouse=True, scope="session")
def sb3_log_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """SB3's ``learn()`` without a TensorBoard folder makes a folder ``SB3-<time>`` in the system's temporary
    directory at every call (as SB3's DQN does): the tests' go to pytest's temporary directory instead."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3")))
        yield


@pytest.fixture
def cli_exit(capsys: pytest.CaptureFixture[str]) -> Callable[[list[str]], tuple[int, str]]:
    """``cli_exit(argv)``: the exit code and stderr of ``sb3-sfgpi ARGV`` run in this process (as the console script
    does: ``sys.exit(main())``; argparse's refusals exit), without a fresh interpreter's 3 s of imports."""
    from sb3_sfgpi.cli import main

    def run(argv: list[str]) -> tuple[int, str]:
        capsys.readouterr()
        try:
            code = main(argv)
        except SystemExit as error:
            code = error.code if isinstance(error.code, int) else 1
        return code, capsys.readouterr().err

    return run


@pytest.fixture
def make_fig1_env() -> Callable[..., Fig1MOMDP]:
    """Factory of the Fig. 1 MOMDP: ``make_fig1_env(one_hot=False)``."""
    return Fig1MOMDP


@pytest.fixture
def make_tabular_sfdqn() -> Callable[..., SFDQN]:
    """Factory of a tabular SFDQN on the Fig. 1 MOMDP with settings that solve it; keyword arguments override."""

    def make(weights: Sequence[float] = (0.5, 0.5), **overrides: Any) -> SFDQN:
        kwargs = {**FIG1_TABULAR_KWARGS, "seed": 0, **overrides}
        return SFDQN("TabularPolicy", Fig1MOMDP(), weights=list(weights), **kwargs)

    return make


@pytest.fixture
def silent_logger() -> Logger:
    """An SB3 logger with no output (``train()`` records to the logger)."""
    return Logger(folder=None, output_formats=[])


def random_mlp_network(
    seed: int, obs_dim: int = 4, n_actions: int = 3, reward_dim: int = 3, net_arch: Sequence[int] = (16, 16)
) -> SFNetwork:
    """A randomly initialised MLP SF network on ``Box(-1, 1, (obs_dim,))`` (seeded)."""
    th.manual_seed(seed)
    observation_space = spaces.Box(-1.0, 1.0, shape=(obs_dim,), dtype=np.float32)
    extractor = FlattenExtractor(observation_space)
    return SFNetwork(
        observation_space,
        spaces.Discrete(n_actions),
        extractor,
        extractor.features_dim,
        reward_dim,
        net_arch=list(net_arch),
    )


def random_tabular_network(
    seed: int, nvec: Sequence[int] = (3, 4, 2), n_actions: int = 3, reward_dim: int = 3
) -> TabularSFNetwork:
    """A tabular SF network on ``MultiDiscrete(nvec)`` with a random (seeded) table."""
    net = TabularSFNetwork(spaces.MultiDiscrete(list(nvec)), spaces.Discrete(n_actions), reward_dim)
    generator = th.Generator().manual_seed(seed)
    net.table.set_dense(th.randn((net.table.n_rows, net.table.width), generator=generator).numpy())
    return net


@pytest.fixture
def make_random_mlp() -> Callable[..., SFNetwork]:
    """Factory of seeded random MLP SF networks (see :func:`random_mlp_network`)."""
    return random_mlp_network


@pytest.fixture
def make_random_tabular() -> Callable[..., TabularSFNetwork]:
    """Factory of seeded random tabular SF networks (see :func:`random_tabular_network`)."""
    return random_tabular_network


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture
def listen() -> Iterator[Callable[[Any, Any], Any]]:
    """``listen(api, listener)`` adds a SUMO step listener and removes it at teardown: libsumo keeps listeners from
    one simulation to the next in the process, where they would read lanes another test's network lacks."""
    added = []

    def add(api: Any, listener: Any) -> Any:
        added.append((api, api.addStepListener(listener)))
        return listener

    yield add
    for api, listener_id in added:
        api.removeStepListener(listener_id)
