"""The runner's joint steps in compiled batches against its step-by-step path: the same tables, replay buffers,
counters, logger records, GPI history and random draws, bit for bit; and Four-Room's packed step against its step."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sfgpi_envs.domains import four_room
from sfgpi_envs.four_room import FourRoomParallelEnv
from stable_baselines3.common.callbacks import BaseCallback
from test_kernels import assert_no_fused_multiply_add

import sb3_sfgpi.compiled_steps
import sb3_sfgpi.tabular.joint_steps
import sb3_sfgpi.tabular.sparse
from sb3_sfgpi.masfols import MASFOLS


class StepByStep(FourRoomParallelEnv):
    """Four-Room without its packed step: the runner steps it in Python, one joint step at a time."""

    packed_dynamics = None


class Stop(BaseCallback):
    """A user's runner-level callback: it reads every step as it happens."""

    def _on_step(self) -> bool:
        return True


@pytest.fixture
def compiled_calls(monkeypatch):
    """The joint steps done by compiled batches (a spy on :meth:`CompiledSteps.run`)."""
    done = []
    run = sb3_sfgpi.compiled_steps.CompiledSteps.run
    monkeypatch.setattr(
        sb3_sfgpi.compiled_steps.CompiledSteps, "run", lambda self, *args: done.append(run(self, *args)) or done[-1]
    )
    monkeypatch.setattr(sb3_sfgpi.tabular.sparse, "INITIAL_CAPACITY", 16)  # tables grow between compiled batches
    return done


def trained(
    env_class: type, learner_kwargs: dict[str, Any], seed: int, callback: Any = None, steps: int = 800
) -> dict[str, Any]:
    """What two short MA-SFOLS iterations of Four-Room leave: every learner's state, the history, numpy's state."""
    preset = four_room()
    kwargs = {**preset["learner_kwargs"], **learner_kwargs}
    algo = MASFOLS(
        env_class(**preset["env_kwargs"]), policy=kwargs.pop("policy"), steps_per_iteration=steps,
        learner_kwargs=kwargs, seed=seed, ols_batch=preset["ols_batch"], validation_weights=4, test_weights=2,
    )  # fmt: skip
    algo.learn(max_iterations=2, callback=callback)
    state: dict[str, Any] = {"numpy": np.random.get_state()[1].tolist(), "history": algo.callback.history}
    for name, learner in algo.runner.learners.items():
        buffer, table = learner.replay_buffer, learner.policy.sf_net.table
        state[name] = {
            "table": (table.stored_rows().tolist(), table.stored_values().tobytes(), table.default.tobytes()),
            "buffer": [part.tobytes() for part in buffer.flat_storage()[:6]] + [buffer.pos, buffer.full],
            "counters": [learner.num_timesteps, learner._n_calls, learner._n_updates, learner._episode_num],
            "rates": [learner.exploration_rate, learner.policy.optimizer.param_groups[0]["lr"]],
            "generator": learner.action_space.np_random.bit_generator.state,
            "logger": dict(learner.logger.name_to_value),
            "obs": learner._last_obs.tolist(),
        }
    state["history"] = [{key: value for key, value in row.items() if "time" not in key} for row in state["history"]]
    return state


@pytest.mark.parametrize(
    "learner_kwargs",
    [
        {"planning_interval": 300},  # plannings and episode ends inside an iteration
        {"learning_starts": 70, "train_freq": 3, "planning_sweeps": 0, "optimistic_init": 0.0},  # uniform warm-up
        {"exploration_steps": 500, "learning_rate": "lin_0.2", "batch_size": 8},  # schedules read ahead
    ],
    ids=["preset", "warm-up", "schedules"],
)
def test_compiled_steps_leave_what_the_step_by_step_path_leaves(compiled_calls, learner_kwargs):
    compiled = trained(FourRoomParallelEnv, learner_kwargs, seed=3)
    assert sum(compiled_calls) > 1_000  # most of the 1,600 joint steps ran compiled
    step_by_step = trained(StepByStep, learner_kwargs, seed=3)
    for key in compiled:
        assert compiled[key] == step_by_step[key], key


def test_the_compiled_joint_steps_have_no_fused_multiply_add(compiled_calls):
    trained(FourRoomParallelEnv, {}, seed=0, steps=200)
    assert compiled_calls and sb3_sfgpi.tabular.joint_steps._kernels
    for kernel in sb3_sfgpi.tabular.joint_steps._kernels.values():
        assert_no_fused_multiply_add(kernel)


class OneActionSpace(FourRoomParallelEnv):
    """Four-Room whose agents share one action space (one generator for both learners' exploration)."""

    def action_space(self, agent: str):
        return self.action_spaces["agent_0"]


def test_learners_exploring_from_one_generator_take_the_step_by_step_path(compiled_calls):
    shared = trained(OneActionSpace, {}, seed=2, steps=300)
    assert compiled_calls == []
    assert shared == trained(type("StepByStepOneSpace", (OneActionSpace,), {"packed_dynamics": None}), {}, 2, steps=300)


def test_a_users_callback_or_a_learners_callback_takes_the_step_by_step_path(compiled_calls):
    trained(FourRoomParallelEnv, {}, seed=0, callback=Stop(), steps=200)
    assert compiled_calls == []
    preset = four_room()
    kwargs = dict(preset["learner_kwargs"])
    algo = MASFOLS(FourRoomParallelEnv(**preset["env_kwargs"]), policy=kwargs.pop("policy"), steps_per_iteration=200,
                   learner_kwargs=kwargs, validation_weights=0, test_weights=2)  # fmt: skip
    algo.runner.learner_callback = lambda name: Stop()
    algo.learn(max_iterations=1)
    assert compiled_calls == []


def test_a_compiled_update_that_diverges_raises_the_step_by_step_error():
    messages = []
    for env_class in (FourRoomParallelEnv, StepByStep):
        with pytest.raises(ValueError, match="diverged") as error:
            trained(env_class, {"learning_rate": 40.0, "planning_sweeps": 0, "optimistic_init": 0.0}, seed=1)
        messages.append(str(error.value))
        raised_by_the_kernel = any(str(entry.path).endswith("sb3_sfgpi/compiled_steps.py") for entry in error.traceback)
        assert raised_by_the_kernel == (env_class is FourRoomParallelEnv)
    assert messages[0] == messages[1]


MODES = st.sampled_from(["xy", "own", "full"])


@settings(max_examples=30, deadline=None)
@given(mode=MODES, max_steps=st.integers(1, 80), seed=st.integers(0, 2**16))
def test_the_packed_step_is_the_envs_step_until_an_episode_ends(mode, max_steps, seed):
    """Stepped alike, the packed state and the env agree after every step; the packed step refuses (returns 1, changes
    nothing) exactly the steps that end an agent's episode."""
    rng = np.random.default_rng(seed)
    packed, env = (
        FourRoomParallelEnv(observation_mode=mode, max_steps=max_steps),
        FourRoomParallelEnv(observation_mode=mode, max_steps=max_steps),
    )
    for _ in range(3):
        packed.reset()
        env.reset()
        while env.agents:
            actions = {agent: int(rng.integers(4)) for agent in env.agents}
            dynamics = packed.packed_dynamics()
            before = dynamics.state.copy()
            chosen = np.array([actions.get(agent, 0) for agent in packed.possible_agents], dtype=np.int64)
            observations = np.zeros((2, len(env.observation_space("agent_0").nvec)), dtype=np.int64)
            rewards = np.zeros((2, 3), dtype=np.float32)
            ended = dynamics.step(dynamics.model, dynamics.constants, dynamics.state, chosen, observations, rewards)
            obs, reward, terminated, truncated, _ = env.step(actions)
            assert ended == (any(terminated.values()) or any(truncated.values()))
            if ended:
                assert np.array_equal(dynamics.state, before)
                packed.step(actions)
            else:
                packed.restore_packed_state(dynamics.state)
                for i, agent in enumerate(packed.possible_agents):
                    if agent in obs:
                        assert np.array_equal(observations[i], obs[agent])
                        assert np.array_equal(rewards[i], reward[agent])
            assert packed.agents == env.agents
            assert np.array_equal(packed.packed_dynamics().state, env.packed_dynamics().state)
            assert all(np.array_equal(packed._observe(i), env._observe(i)) for i in range(2))


@settings(max_examples=30, deadline=None)
@given(mode=MODES, max_steps=st.integers(1, 80), seed=st.integers(0, 2**16))
def test_the_packed_episode_step_is_the_envs_step_to_the_episodes_end(mode, max_steps, seed):
    """Stepped alike through whole episodes (goal entries and the step limit included), the packed state is the env's
    after every step, the live agents' observations and every moving agent's reward are the env's, and the bits
    returned are the agents still live."""
    rng = np.random.default_rng(seed)
    env = FourRoomParallelEnv(observation_mode=mode, max_steps=max_steps)
    for _ in range(3):
        env.reset()
        dynamics = env.packed_dynamics()
        while env.agents:
            moving = list(env.agents)
            actions = {agent: int(rng.integers(4)) for agent in moving}
            chosen = np.array([actions.get(agent, 0) for agent in env.possible_agents], dtype=np.int64)
            observations = np.zeros((2, len(env.observation_space("agent_0").nvec)), dtype=np.int64)
            rewards = np.zeros((2, 3), dtype=np.float32)
            live = dynamics.episode_step(
                dynamics.model, dynamics.constants, dynamics.state, chosen, observations, rewards
            )
            obs, reward, _, _, _ = env.step(actions)
            assert [bool(live >> i & 1) for i in range(2)] == [agent in env.agents for agent in env.possible_agents]
            assert np.array_equal(dynamics.state, env.packed_dynamics().state)
            for i, agent in enumerate(env.possible_agents):
                if agent in moving:
                    assert np.array_equal(rewards[i], reward[agent])
                if agent in env.agents:
                    assert np.array_equal(observations[i], obs[agent])
