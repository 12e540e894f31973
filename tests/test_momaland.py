"""MOMAland's environments as they come: composite observations, swapped flags, their API test on our wrappers."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import parallel_api_test

from sb3_sfgpi import MASFOLS, FlattenObservations, SelfFirstAgentIds, SwapTerminationsTruncations
from sb3_sfgpi.common.parallel_wrappers import needs_flattening

moitem_gathering_v0 = pytest.importorskip("momaland.envs.item_gathering.moitem_gathering_v0")
mobeach_v0 = pytest.importorskip("momaland.envs.beach.mobeach_v0")

SMALL = dict(steps_per_iteration=200, test_weights=3, learner_kwargs=dict(learning_starts=50, batch_size=16))
TINY_MAP = np.array([[1, 3, 4], [4, 3, 1]])  # two agents, two items of each of two kinds: gathered within a few steps


def swap_warnings(caught: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in caught if "SwapTerminationsTruncations" in str(w.message)]


def test_item_gathering_trains_with_its_tuple_observations_flattened(tmp_path):
    env = SwapTerminationsTruncations(moitem_gathering_v0.parallel_env())
    assert needs_flattening(env)  # Tuple(Discrete, Box): SB3's buffers refuse it
    model = MASFOLS(env, policy="MlpPolicy", weights="ols", seed=0, run_dir=tmp_path, **SMALL).learn(max_iterations=2)
    assert isinstance(model.policy_set.observation_space, spaces.Box)
    assert model.policy_set.observation_space.shape == (2 + 8 * 8,)  # the agent id one-hot, then the map
    assert len(model.history) == 2 and 1 <= len(model.policy_set) <= 4
    assert all(np.isfinite(row["mean_return"]) for row in model.history)
    assert model.callback.schedule.ols.values  # OLS received the new policies' values
    obs, _ = FlattenObservations(moitem_gathering_v0.parallel_env()).reset(seed=1)
    actions, _ = model.policy_set.predict([obs[a] for a in env.possible_agents], w=[0.2, 0.3, 0.5])
    assert actions.shape == (2,) and all(0 <= a < 5 for a in actions)


def test_beach_trains_with_three_agents():
    env = SwapTerminationsTruncations(mobeach_v0.parallel_env(num_agents=3, num_timesteps=5))
    model = MASFOLS(env, policy="MlpPolicy", weights="ols", seed=0, **SMALL).learn(max_iterations=2)
    assert model.history[0]["weights_trained"].keys() == {"agent_0", "agent_1", "agent_2"}
    assert len(model.policy_set) >= 1 and np.isfinite(model.history[-1]["mean_return"])
    assert len(model.history) == 2 or model.callback.schedule.ols.ended  # OLS may end after the extrema (d = 2)


def test_swapped_flags_are_warned_about_once_and_the_wrapper_silences_it():
    for wrapped, expected in ((False, 1), (True, 0)):
        env = moitem_gathering_v0.parallel_env(initial_map=TINY_MAP, num_timesteps=50)
        env = SwapTerminationsTruncations(env) if wrapped else env
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            MASFOLS(env, policy="MlpPolicy", weights="ols", seed=0, **SMALL).learn(max_iterations=1)
        assert len(swap_warnings(caught)) == expected


def test_our_wrappers_pass_pettingzoos_api_test():
    parallel_api_test(FlattenObservations(moitem_gathering_v0.parallel_env()), num_cycles=30)
    parallel_api_test(SelfFirstAgentIds(moitem_gathering_v0.parallel_env()), num_cycles=30)
    parallel_api_test(SwapTerminationsTruncations(mobeach_v0.parallel_env(num_agents=3)), num_cycles=30)


def test_each_agent_sees_itself_first_and_the_others_in_their_order():
    three = np.array([[1, 3, 1], [4, 1, 3]])  # three agents (1), items of two kinds
    raw = moitem_gathering_v0.parallel_env(initial_map=three, num_timesteps=50)
    wrapped = SelfFirstAgentIds(moitem_gathering_v0.parallel_env(initial_map=three, num_timesteps=50))
    seen, views = raw.reset(seed=0)[0], wrapped.reset(seed=0)[0]
    rng = np.random.default_rng(0)
    for _ in range(5):
        for agent, (own, board) in seen.items():
            view_id, view = views[agent]
            assert view_id == -1 and view.shape == board.shape
            assert np.array_equal(view == -1, board == own)  # itself where it stands
            others = sorted(int(-v) for v in np.unique(board[(board < 0) & (board != own)]))
            for label, index in enumerate(others, start=2):  # the others, -2, -3, ... in their order
                assert np.array_equal(view == -label, board == -index)
            assert np.array_equal(view[board >= 0], board[board >= 0])  # items and empty cells as they were
        actions = {agent: int(rng.integers(5)) for agent in raw.agents}
        seen, views = raw.step(actions)[0], wrapped.step(actions)[0]


def test_self_first_ids_refuse_observations_without_agent_ids():
    with pytest.raises(ValueError, match="agent id, map"):
        SelfFirstAgentIds(mobeach_v0.parallel_env(num_agents=3))


def test_flattening_keeps_flat_spaces_as_they_are():
    env = mobeach_v0.parallel_env(num_agents=3)
    assert not needs_flattening(env)


def test_four_room_passes_momalands_api_test():
    from momaland.test.api_test import api_test
    from momaland.utils.conversions import mo_parallel_to_aec
    from sfgpi_envs import FourRoomParallelEnv

    api_test(mo_parallel_to_aec(FourRoomParallelEnv()), num_cycles=300)  # raises AssertionError where it fails
