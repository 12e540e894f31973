"""SB3's tools with vector rewards: mo_evaluate_policy, MOEvalCallback, GPIPolicy.for_weights, make_mo_vec_env."""

from __future__ import annotations

import csv
import sys
import warnings

import gymnasium as gym
import mo_gymnasium
import numpy as np
import pytest
from conftest import BAD_WEIGHTS, FIG1_TABULAR_KWARGS, FIG1_TABULAR_STEPS
from mo_gymnasium.wrappers import LinearReward
from momdp import ALL_POLICIES, Fig1MOMDP, exact_tabular_network, optimal_value, policy_value
from stable_baselines3.common.callbacks import BaseCallback, StopTrainingOnRewardThreshold
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

from sb3_sfgpi import SFDQN, GPIPolicy, MOEvalCallback, make_mo_vec_env, mo_evaluate_policy
from sb3_sfgpi.common.vec_env import MODummyVecEnv, MOMonitor, import_registering_package

DST = "deep-sea-treasure-v0"
RIGHT, DOWN = 3, 1
#: Deep Sea Treasure: the treasure at the bottom of each of the first columns and the steps it takes to reach it
#: from the start, going right along the surface first, then straight down.
DST_TREASURES = [(0, 0.7, 1), (1, 8.2, 3), (2, 11.5, 5)]
#: Settings under which tabular SFDQN finds a treasure of Deep Sea Treasure in a few thousand steps.
DST_TABULAR_KWARGS = dict(
    learning_rate=0.5, batch_size=1, train_freq=1, learning_starts=0, exploration_fraction=0.5, buffer_size=5_000
)


class ColumnDiver:
    """A scripted policy: right along the surface up to ``column``, then down to the treasure below it."""

    def __init__(self, column: int):
        self.column = column

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        observation = np.asarray(observation)  # (row, column), one or a batch
        return np.where(observation[..., 1] < self.column, RIGHT, DOWN), state


class OffsetReward(gym.Wrapper):
    """Adds ``offset`` to the last objective of every reward: tags the episodes of one env of a VecEnv."""

    def __init__(self, env: gym.Env, offset: float):
        super().__init__(env)
        self.offset = offset

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        reward = np.array(reward, dtype=np.float32)
        reward[-1] += self.offset
        return obs, reward, terminated, truncated, info


# --------------------------------------------------------------------------------------------------------------
# mo_evaluate_policy
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("column", "treasure", "steps"), DST_TREASURES)
def test_a_scripted_policy_gets_its_known_treasure(column, treasure, steps):
    policy = ColumnDiver(column)
    mean, std = mo_evaluate_policy(policy, mo_gymnasium.make(DST), n_eval_episodes=3)
    np.testing.assert_allclose(mean, [treasure, -steps], rtol=1e-6)
    np.testing.assert_array_equal(std, [0.0, 0.0])
    returns, lengths = mo_evaluate_policy(
        policy, mo_gymnasium.make(DST), n_eval_episodes=3, return_episode_rewards=True
    )
    assert returns.shape == (3, 2)
    np.testing.assert_array_equal(lengths, [steps] * 3)
    # Discounted: the treasure comes at the last step, each step costs -1.
    mean, _ = mo_evaluate_policy(policy, mo_gymnasium.make(DST), n_eval_episodes=2, gamma=0.9)
    np.testing.assert_allclose(mean, [0.9 ** (steps - 1) * treasure, -sum(0.9**t for t in range(steps))], rtol=1e-6)


def test_episodes_are_shared_among_envs_as_sb3_does():
    # Env i adds i to the time penalty of each of the 3 steps of its episodes: each episode tells its env.
    venv = MODummyVecEnv([lambda i=i: MOMonitor(OffsetReward(mo_gymnasium.make(DST), i)) for i in range(3)])
    returns, lengths = mo_evaluate_policy(ColumnDiver(1), venv, n_eval_episodes=7, return_episode_rewards=True)
    assert returns.shape == (7, 2) and lengths.shape == (7,)
    env_of_episode = np.round((returns[:, 1] + 3) / 3).astype(int)
    np.testing.assert_array_equal(np.bincount(env_of_episode, minlength=3), [2, 2, 3])  # (7 + i) // 3


def test_the_monitor_return_is_the_one_before_later_wrappers():
    # As SB3's evaluate_policy: a wrapper applied after the monitor does not change the undiscounted return.
    env = OffsetReward(MOMonitor(mo_gymnasium.make(DST)), 100.0)
    mean, _ = mo_evaluate_policy(ColumnDiver(0), env, n_eval_episodes=1)
    np.testing.assert_allclose(mean, [0.7, -1.0], rtol=1e-6)


@pytest.mark.parametrize(
    ("model", "env", "kwargs", "message"),
    [
        pytest.param(ColumnDiver(0), lambda: mo_gymnasium.make(DST), {"n_eval_episodes": 0}, "n_eval_episodes", id="0"),
        pytest.param(ColumnDiver(0), lambda: mo_gymnasium.make(DST), {"n_eval_episodes": 2.5}, "integer", id="float"),
        pytest.param(ColumnDiver(0), lambda: mo_gymnasium.make(DST), {"gamma": 0.0}, "gamma", id="gamma"),
        pytest.param(ColumnDiver(0), lambda: gym.make("CartPole-v1"), {}, "scalar rewards", id="scalar-env"),
        pytest.param(
            ColumnDiver(0), lambda: DummyVecEnv([lambda: mo_gymnasium.make(DST)]), {}, "MODummyVecEnv", id="dummy"
        ),
        pytest.param(object(), lambda: mo_gymnasium.make(DST), {}, "no predict", id="no-predict"),
        pytest.param(GPIPolicy(), lambda: mo_gymnasium.make(DST), {}, "for_weights", id="gpi-unbound"),
    ],
)
def test_mo_evaluate_policy_refuses_bad_inputs(model, env, kwargs, message):
    with pytest.raises(ValueError, match=message):
        mo_evaluate_policy(model, env(), **kwargs)


# --------------------------------------------------------------------------------------------------------------
# GPIPolicy.for_weights: SB3's own evaluate_policy
# --------------------------------------------------------------------------------------------------------------


def sb3_return(predictor, w) -> float:
    mean, _ = evaluate_policy(predictor, LinearReward(Fig1MOMDP(), weight=np.asarray(w)), n_eval_episodes=2, warn=False)
    return float(mean)


@pytest.fixture(scope="module")
def trained_set() -> GPIPolicy:
    """GPI over two tabular learners trained on the Fig. 1 MOMDP for opposite weights."""
    return GPIPolicy(
        SFDQN("TabularPolicy", Fig1MOMDP(), weights=w, seed=0, **FIG1_TABULAR_KWARGS).learn(FIG1_TABULAR_STEPS)
        for w in ([0.9, 0.1], [0.1, 0.9])
    )


@pytest.mark.parametrize("w", [[1.0, 0.0], [0.3, 0.7], [0.6, 0.4]])
def test_sb3_evaluate_policy_runs_gpi_over_trained_policies(w, trained_set):
    predictor = trained_set.for_weights(w)
    mean, _ = mo_evaluate_policy(predictor, Fig1MOMDP(), n_eval_episodes=2)
    assert sb3_return(predictor, w) == pytest.approx(float(np.dot(w, mean)))
    np.testing.assert_array_equal(predictor.weights, w)


@pytest.mark.parametrize("w", [[1.0, 0.0], [0.3, 0.7], [0.5, 0.5]])
def test_gpi_over_every_policy_is_optimal_in_sb3_evaluate_policy(w):
    policy_set = GPIPolicy()
    for actions in ALL_POLICIES:
        policy_set.add(exact_tabular_network(actions), weights=[0.5, 0.5], value=policy_value(actions))
    assert sb3_return(policy_set.for_weights(w), w) == pytest.approx(optimal_value(w), abs=1e-4)


@pytest.mark.parametrize(("weights", "message"), BAD_WEIGHTS)
def test_for_weights_refuses_bad_weights(weights, message):
    policy_set = GPIPolicy()
    policy_set.add(exact_tabular_network(ALL_POLICIES[0]), weights=[0.5, 0.5])
    with pytest.raises(ValueError, match=message):
        policy_set.for_weights(weights)
    with pytest.raises(ValueError, match="empty"):
        GPIPolicy().for_weights([0.5, 0.5])


# --------------------------------------------------------------------------------------------------------------
# MOEvalCallback
# --------------------------------------------------------------------------------------------------------------


def dst_learner(env=None, weights=(0.9, 0.1), **kwargs) -> SFDQN:
    env = mo_gymnasium.make(DST) if env is None else env
    return SFDQN("TabularPolicy", env, weights=list(weights), seed=0, **{**DST_TABULAR_KWARGS, **kwargs})


def read_progress(path) -> list[dict[str, str]]:
    with open(path, newline="") as file:
        return [row for row in csv.DictReader(file) if row.get("eval/mean_reward")]


def test_eval_callback_logs_saves_and_keeps_the_best_model(tmp_path):
    w = np.array([0.9, 0.1])
    model = dst_learner(weights=w)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    callback = MOEvalCallback(
        mo_gymnasium.make(DST), n_eval_episodes=2, eval_freq=500, log_path=str(tmp_path),
        best_model_save_path=str(tmp_path), verbose=0,
    )  # fmt: skip
    model.learn(1_500, callback=callback)

    rows = read_progress(tmp_path / "progress.csv")
    assert [int(row["time/total_timesteps"]) for row in rows] == [500, 1_000, 1_500]
    evaluations = np.load(tmp_path / "evaluations.npz")
    np.testing.assert_array_equal(evaluations["timesteps"], [500, 1_000, 1_500])
    assert evaluations["results"].shape == (3, 2, 2) and evaluations["ep_lengths"].shape == (3, 2)
    np.testing.assert_allclose(evaluations["weights"], [w] * 3)
    for row, results in zip(rows, evaluations["results"], strict=True):
        per_objective = [float(row[f"eval/mean_reward_{i}"]) for i in range(2)]
        np.testing.assert_allclose(per_objective, results.mean(axis=0), rtol=1e-6)
        assert float(row["eval/mean_reward"]) == pytest.approx(float(w @ results.mean(axis=0)))
        assert float(row["eval/mean_ep_length"]) > 0

    best = SFDQN.load(tmp_path / "best_model.zip", device="cpu")
    best_mean, _ = mo_evaluate_policy(best, mo_gymnasium.make(DST), n_eval_episodes=2)
    best_logged = max(float(row["eval/mean_reward"]) for row in rows)
    assert float(w @ best_mean) == pytest.approx(best_logged) == pytest.approx(callback.best_mean_reward)


class CountCalls(BaseCallback):
    def _on_step(self) -> bool:
        return True


def test_eval_callback_runs_the_callbacks_of_a_new_best_and_of_every_evaluation():
    model = dst_learner()
    after_eval = CountCalls()
    callback = MOEvalCallback(
        mo_gymnasium.make(DST), callback_after_eval=after_eval, n_eval_episodes=1, eval_freq=200, verbose=0
    )
    model.learn(600, callback=callback)
    assert after_eval.n_calls == 3
    # A threshold every return beats: training stops at the first evaluation.
    stop = StopTrainingOnRewardThreshold(reward_threshold=-1_000.0)
    model = dst_learner()
    model.learn(
        1_000, callback=MOEvalCallback(mo_gymnasium.make(DST), stop, n_eval_episodes=1, eval_freq=200, verbose=0)
    )
    assert model.num_timesteps == 200


@pytest.mark.parametrize(
    ("env", "kwargs", "message"),
    [
        pytest.param(lambda: gym.make("CartPole-v1"), {}, "scalar rewards", id="scalar-env"),
        pytest.param(lambda: mo_gymnasium.make(DST), {"n_eval_episodes": 0}, "n_eval_episodes", id="0-episodes"),
        pytest.param(lambda: mo_gymnasium.make(DST), {"weights": [0.5, 0.3, 0.2]}, "length", id="bad-weights"),
    ],
)
def test_eval_callback_refuses_bad_inputs(env, kwargs, message):
    with pytest.raises(ValueError, match=message):
        MOEvalCallback(env(), **kwargs)


class WithoutWeights:
    """A model as SB3's callbacks see it, without ``weights``."""

    logger = None

    def __init__(self, env):
        self.env = env

    def get_env(self):
        return self.env


def test_eval_callback_needs_weights_to_scalarise():
    env = make_mo_vec_env(DST)
    with pytest.raises(ValueError, match="weights="):
        MOEvalCallback(mo_gymnasium.make(DST), verbose=0).init_callback(WithoutWeights(env))  # type: ignore[arg-type]
    MOEvalCallback(mo_gymnasium.make(DST), weights=[0.5, 0.5], verbose=0).init_callback(WithoutWeights(env))


# --------------------------------------------------------------------------------------------------------------
# make_mo_vec_env
# --------------------------------------------------------------------------------------------------------------

VEC_ENV_CLASSES = [
    pytest.param(MODummyVecEnv, {}, id="MODummyVecEnv"),
    pytest.param(SubprocVecEnv, {"start_method": "fork"}, id="SubprocVecEnv"),
]


def first_steps(vec_env_cls, vec_env_kwargs, seed):
    venv = make_mo_vec_env(
        "mo-mountaincar-v0", n_envs=2, seed=seed, vec_env_cls=vec_env_cls, vec_env_kwargs=vec_env_kwargs
    )
    try:
        observations = venv.reset()
        _, rewards, _, _ = venv.step(np.array([0, 2]))
        return observations, rewards, venv.get_attr("reward_dim")
    finally:
        venv.close()


@pytest.mark.parametrize(("vec_env_cls", "vec_env_kwargs"), VEC_ENV_CLASSES)
def test_make_mo_vec_env_is_seeded_per_env(vec_env_cls, vec_env_kwargs):
    observations, rewards, reward_dims = first_steps(vec_env_cls, vec_env_kwargs, seed=3)
    assert rewards.shape == (2, 3) and reward_dims == [3, 3]  # monitored: MOMonitor.reward_dim
    again, rewards_again, _ = first_steps(vec_env_cls, vec_env_kwargs, seed=3)
    np.testing.assert_array_equal(again, observations)
    np.testing.assert_array_equal(rewards_again, rewards)
    assert not np.array_equal(observations[0], observations[1])  # seed + rank
    other, _, _ = first_steps(vec_env_cls, vec_env_kwargs, seed=4)
    np.testing.assert_array_equal(other[0], observations[1])  # env 0 of seed 4 is env 1 of seed 3


@pytest.mark.parametrize(("vec_env_cls", "vec_env_kwargs"), VEC_ENV_CLASSES)
def test_sfdqn_learns_from_make_mo_vec_env(vec_env_cls, vec_env_kwargs):
    venv = make_mo_vec_env(DST, n_envs=2, seed=0, vec_env_cls=vec_env_cls, vec_env_kwargs=vec_env_kwargs)
    try:
        model = dst_learner(venv).learn(2_000)
    finally:
        venv.close()
    assert model.num_timesteps == 2_000 and model.n_envs == 2
    returns, lengths = mo_evaluate_policy(model, mo_gymnasium.make(DST), n_eval_episodes=1, return_episode_rewards=True)
    assert returns[0, 0] > 0 and lengths[0] < 100  # reaches a treasure before the time limit


def test_make_mo_vec_env_takes_a_callable_its_kwargs_and_a_wrapper():
    venv = make_mo_vec_env(
        Fig1MOMDP, n_envs=2, env_kwargs={"one_hot": True}, wrapper_class=gym.wrappers.TimeLimit,
        wrapper_kwargs={"max_episode_steps": 2},
    )  # fmt: skip
    assert venv.reset().shape == (2, 5)
    venv.step(np.array([0, 1]))
    _, _, dones, infos = venv.step(np.array([0, 1]))
    assert dones.all() and all("episode" not in info for info in infos)  # truncated after the monitor


@pytest.mark.parametrize(
    ("env_id", "kwargs", "error", "message"),
    [
        pytest.param("CartPole-v1", {}, ValueError, "scalar rewards", id="scalar-env"),
        pytest.param("no-such-env-v0", {}, ValueError, "neither", id="unknown-id"),
        pytest.param(DST, {"n_envs": 0}, ValueError, "n_envs", id="0-envs"),
        pytest.param(DST, {"vec_env_cls": DummyVecEnv}, ValueError, "MODummyVecEnv", id="DummyVecEnv"),
    ],
)
def test_make_mo_vec_env_refuses_bad_inputs(env_id, kwargs, error, message):
    with pytest.raises(error, match=message):
        make_mo_vec_env(env_id, **kwargs)


def test_make_mo_vec_env_without_mo_gymnasium_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "mo_gymnasium", None)  # import mo_gymnasium raises ImportError
    with pytest.raises(ImportError, match="install mo-gymnasium"):
        make_mo_vec_env("not-registered-v0")


def test_registering_mo_gymnasium_hides_only_pygames_pkg_resources_warning(tmp_path, monkeypatch):
    """Under a recent setuptools, pygame's import warns that pkg_resources is deprecated; a CLI error stays one line."""
    (tmp_path / "warns_on_import.py").write_text(
        "import warnings\n"
        "warnings.warn('pkg_resources is deprecated as an API. See https://setuptools.pypa.io', UserWarning)\n"
        "warnings.warn('something the user must see', UserWarning)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import_registering_package("warns_on_import")
    assert [str(w.message) for w in caught] == ["something the user must see"]
