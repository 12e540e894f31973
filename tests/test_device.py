"""Devices: ``device="auto"`` works on every machine (tables on the CPU, MLPs on CUDA where there is one), and a
policy set saved on one device loads on another with the same predictions.

The rule is unit-tested for both answers of "is CUDA available"; the tests marked ``cuda`` need a GPU and skip
without one.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch as th
from conftest import FIG1_TABULAR_KWARGS
from momdp import Fig1MOMDP

from sb3_sfgpi.common.device import resolve_device
from sb3_sfgpi.gpi import CorruptPolicySetError, GPIPolicy
from sb3_sfgpi.sfdqn import SFDQN

STEPS = 300
MLP_KWARGS = dict(
    policy_kwargs=dict(net_arch=[16]),
    learning_starts=50,
    batch_size=16,
    train_freq=1,
    buffer_size=1_000,
    target_update_interval=100,
    seed=0,
)


def tabular_sfdqn(**kwargs) -> SFDQN:
    return SFDQN("TabularPolicy", Fig1MOMDP(), **{**FIG1_TABULAR_KWARGS, "seed": 0, **kwargs})


def mlp_sfdqn(**kwargs) -> SFDQN:
    return SFDQN("MlpPolicy", Fig1MOMDP(one_hot=True), **{**MLP_KWARGS, **kwargs})


def parameters(model: SFDQN) -> list[th.Tensor]:
    return [p.detach().cpu().clone() for p in model.policy.sf_net.parameters()]


def observations(policy_set: GPIPolicy, n: int = 32) -> np.ndarray:
    space = policy_set.observation_space
    space.seed(3)
    return np.stack([space.sample() for _ in range(n)])


def assert_same_predictions(a: GPIPolicy, b: GPIPolicy) -> None:
    obs = observations(a)
    for w in [*np.eye(a.reward_dim), np.linspace(1.0, 2.0, a.reward_dim)]:
        np.testing.assert_allclose(a.q_values(obs, w), b.q_values(obs, w), rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(a.predict(obs, w)[0], b.predict(obs, w)[0])


def filled_set(make, device: str = "cpu") -> GPIPolicy:
    policy_set = GPIPolicy(device=device)
    for seed in range(3):
        policy_set.add(make(seed), weights=[1.0, 1.0, 1.0])
    return policy_set


# --------------------------------------------------------------------------------------------------------------
# The rule
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "requested, tabular, cuda_available, expected",
    [
        ("auto", True, True, "cpu"),
        ("auto", True, False, "cpu"),
        ("auto", False, True, "cuda"),
        ("auto", False, False, "cpu"),
        ("cpu", True, True, "cpu"),
        (th.device("cpu"), True, True, "cpu"),
        ("cpu", False, True, "cpu"),
        ("cuda", False, True, "cuda"),
        ("cuda:1", False, True, "cuda:1"),
        (th.device("cuda"), False, True, "cuda"),
        ("cuda", False, False, "cpu"),  # as SB3's get_device
    ],
)
def test_resolve_device(requested, tabular, cuda_available, expected):
    assert resolve_device(requested, tabular, cuda_available) == th.device(expected)


@pytest.mark.parametrize("requested", ["cuda", "cuda:0", th.device("cuda"), "meta"])
@pytest.mark.parametrize("cuda_available", [True, False])
def test_tables_refuse_any_device_but_the_cpu_on_every_machine(requested, cuda_available):
    with pytest.raises(ValueError, match="run on the CPU only"):
        resolve_device(requested, tabular=True, cuda_available=cuda_available)


def test_resolve_device_asks_torch_by_default():
    assert resolve_device("auto") == th.device("cuda" if th.cuda.is_available() else "cpu")
    assert resolve_device("auto", tabular=True) == th.device("cpu")


# --------------------------------------------------------------------------------------------------------------
# SFDQN
# --------------------------------------------------------------------------------------------------------------


def test_tabular_sfdqn_trains_with_auto():
    model = tabular_sfdqn(device="auto")
    assert model.device == th.device("cpu") and model.policy.sf_net.device == th.device("cpu")
    model.learn(STEPS)
    assert model.num_timesteps == STEPS and len(model.policy.sf_net.table) > 0


def test_mlp_sfdqn_trains_with_auto():
    model = mlp_sfdqn(device="auto")
    assert model.device == resolve_device("auto")
    before = parameters(model)
    model.learn(STEPS)
    assert model.num_timesteps == STEPS and model._n_updates > 0
    assert any(not th.equal(a, b) for a, b in zip(before, parameters(model), strict=True))
    assert model.predict(np.eye(5, dtype=np.float32), deterministic=True)[0].shape == (5,)


@pytest.mark.parametrize("device", ["cuda", th.device("cuda:0")])
def test_tabular_sfdqn_refuses_an_explicit_gpu_on_every_machine(device):
    with pytest.raises(ValueError, match="TabularPolicy.*CPU only"):
        tabular_sfdqn(device=device)


def test_tabular_sfdqn_loads_with_auto(tmp_path):
    model = tabular_sfdqn()
    model.learn(100)
    model.save(tmp_path / "model.zip")
    loaded = SFDQN.load(tmp_path / "model.zip", device="auto")
    assert loaded.device == th.device("cpu")
    np.testing.assert_array_equal(loaded.policy.sf_net.table.dense(), model.policy.sf_net.table.dense())


# --------------------------------------------------------------------------------------------------------------
# GPIPolicy
# --------------------------------------------------------------------------------------------------------------


def test_tabular_set_with_auto_stays_on_the_cpu_with_its_numpy_path(make_random_tabular):
    policy_set = filled_set(make_random_tabular, device="auto")
    assert policy_set.device == th.device("cpu")
    assert all(net.device == th.device("cpu") for net in policy_set.networks)
    assert policy_set._stack().tables_numpy is not None
    assert_same_predictions(policy_set, filled_set(make_random_tabular))


def test_mlp_set_with_auto_goes_where_mlps_go(make_random_mlp):
    policy_set = filled_set(make_random_mlp, device="auto")
    assert policy_set.device == resolve_device("auto")
    assert all(p.device.type == policy_set.device.type for net in policy_set.networks for p in net.parameters())
    assert_same_predictions(policy_set, filled_set(make_random_mlp))


def test_tabular_set_refuses_an_explicit_gpu(make_random_tabular):
    policy_set = GPIPolicy(device="cuda")
    with pytest.raises(ValueError, match="CPU only"):
        policy_set.add(make_random_tabular(0), weights=[1.0, 1.0, 1.0])
    assert len(policy_set) == 0


def test_moving_a_tabular_set_to_a_gpu_is_refused_and_leaves_it_usable(make_random_tabular):
    policy_set = filled_set(make_random_tabular)
    with pytest.raises(ValueError, match="CPU only"):
        policy_set.to("cuda")
    assert policy_set.device == th.device("cpu")
    assert_same_predictions(policy_set, filled_set(make_random_tabular))


def test_loading_a_tabular_set_on_a_gpu_is_refused_not_called_corrupt(tmp_path, make_random_tabular):
    filled_set(make_random_tabular).save(tmp_path / "set")
    with pytest.raises(ValueError, match="CPU only") as raised:
        GPIPolicy.load(tmp_path / "set", device="cuda")
    assert not isinstance(raised.value, CorruptPolicySetError)
    assert GPIPolicy.load(tmp_path / "set", device="auto").device == th.device("cpu")


@pytest.mark.parametrize("kind", ["mlp", "tabular"])
def test_set_saved_and_loaded_with_auto_predicts_the_same(tmp_path, kind, make_random_mlp, make_random_tabular):
    policy_set = filled_set(make_random_mlp if kind == "mlp" else make_random_tabular, device="auto")
    policy_set.save(tmp_path / "set")
    loaded = GPIPolicy.load(tmp_path / "set", device="auto")
    assert loaded.device == policy_set.device
    assert_same_predictions(loaded, policy_set)


# --------------------------------------------------------------------------------------------------------------
# On a GPU
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
def test_mlp_sfdqn_with_auto_learns_on_cuda():
    model = mlp_sfdqn(device="auto")
    assert model.device.type == "cuda"
    assert all(p.device.type == "cuda" for p in model.policy.parameters())
    before = parameters(model)
    model.learn(STEPS)
    assert any(not th.equal(a, b) for a, b in zip(before, parameters(model), strict=True))


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
def test_tabular_sfdqn_with_auto_stays_on_the_cpu_beside_a_gpu(tmp_path):
    model = tabular_sfdqn(device="auto")
    assert model.device.type == "cpu" and model.policy.sf_net.device.type == "cpu"
    model.learn(STEPS)
    model.save(tmp_path / "model.zip")
    assert SFDQN.load(tmp_path / "model.zip", device="auto").device.type == "cpu"


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("saved_on, loaded_on", [("cuda", "cpu"), ("cpu", "cuda"), ("cuda", "auto")])
def test_mlp_set_saved_on_one_device_loads_on_another(tmp_path, make_random_mlp, saved_on, loaded_on):
    policy_set = filled_set(make_random_mlp, device=saved_on)
    policy_set.save(tmp_path / "set")
    loaded = GPIPolicy.load(tmp_path / "set", device=loaded_on)
    assert loaded.device == resolve_device(loaded_on)
    assert all(p.device.type == loaded.device.type for net in loaded.networks for p in net.parameters())
    assert_same_predictions(loaded, policy_set)


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
def test_tabular_set_loads_on_the_cpu_beside_a_gpu(tmp_path, make_random_tabular):
    filled_set(make_random_tabular).save(tmp_path / "set")
    loaded = GPIPolicy.load(tmp_path / "set", device="auto")
    assert loaded.device.type == "cpu" and loaded._stack().tables_numpy is not None
    assert_same_predictions(loaded, filled_set(make_random_tabular))


@pytest.mark.cuda
@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA GPU")
def test_networks_added_from_a_learner_on_another_device_are_moved():
    model = mlp_sfdqn(device="cuda")
    model.learn(STEPS)
    on_cpu, on_cuda = GPIPolicy([model], device="cpu"), GPIPolicy([model], device="cuda")
    assert all(p.device.type == "cpu" for net in on_cpu.networks for p in net.parameters())
    assert all(p.device.type == "cuda" for net in on_cuda.networks for p in net.parameters())
    assert_same_predictions(on_cpu, on_cuda)
