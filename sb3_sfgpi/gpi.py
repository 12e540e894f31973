"""Generalized policy improvement over a set of successor-feature policies.

``π(s) = argmax_a max_{π ∈ Π} w · ψ^π(s, a)``: any preference ``w`` gets a behaviour from the set,
without training. All networks of a set share one architecture and are evaluated in a single batched
pass over their stacked parameters, built once after the set changes:

* tabular sets: one gather of the observed rows from a ``(S, P·A·d)`` stack of the tables;
* MLP sets (parameter-free features extractor, ``Linear`` layers and activations): the features are
  extracted once and every layer is one batched matrix product over the ``P`` networks;
* anything else: ``torch.func.stack_module_state`` + ``vmap`` over ``functional_call``.

The three give the same ``ψ`` (the specialised ones skip the per-call overhead of ``vmap``, about a
millisecond per decision; see ``benchmarks/bench_gpi.py``).

Policy-set directory format (``GPIPolicy.save`` / ``GPIPolicy.load``)::

    manifest.json     {"format": "sb3-sfgpi/policy-set", "version": 1, "reward_dim": d,
                       "observation_space": {...}, "action_space": {...}, "network": {...},
                       "policies": [{"file": "policy_000.pt", "weights": [...], "value": [...] | null,
                                     "agent": str | null, "iteration": int | null}, ...]}
    policy_000.pt     the state dict of one SF network (tensors only, read with weights_only=True); a table is
                      stored as its non-zero rows: "table.rows" (their indices), "table.values" (the rows)
                      and "table.shape" instead of the dense "table.weight" (which is read too)

The manifest is written last and atomically, so a directory whose save was interrupted keeps the
previous manifest or has none. Loading never runs code from the directory.
"""

from __future__ import annotations

import copy
import io
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.utils import is_vectorized_observation
from torch import nn
from torch.func import functional_call, stack_module_state

from sb3_sfgpi.common.device import resolve_device
from sb3_sfgpi.common.serialization import (
    atomic_write_bytes,
    atomic_write_json,
    read_json,
    space_from_dict,
    space_to_dict,
)
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.sfdqn.policies import SFNetwork, TabularSFNetwork
from sb3_sfgpi.sfdqn.sfdqn import SFDQN

FORMAT = "sb3-sfgpi/policy-set"
VERSION = 1
MANIFEST = "manifest.json"
_ACTIVATIONS = {name: getattr(nn, name) for name in ("ReLU", "Tanh", "ELU", "LeakyReLU", "GELU", "SiLU", "Identity")}


class CorruptPolicySetError(ValueError):
    """A policy-set directory that cannot be loaded: missing, truncated, inconsistent or foreign files."""


@dataclass(frozen=True)
class PolicyInfo:
    """
    What the set knows of one policy besides its network.

    :param weights: the preference weights it was trained for
    :param value: its value vector ``V^π`` (``None`` if not evaluated)
    :param agent: the agent that learned it
    :param iteration: the OLS iteration that produced it
    """

    weights: np.ndarray
    value: np.ndarray | None = None
    agent: str | None = None
    iteration: int | None = None

    def to_dict(self, file: str) -> dict[str, Any]:
        return {
            "file": file,
            "weights": self.weights.tolist(),
            "value": None if self.value is None else self.value.tolist(),
            "agent": self.agent,
            "iteration": self.iteration,
        }


def network_spec(net: nn.Module) -> dict[str, Any]:
    """
    Plain-data description of an SF network's architecture (enough to rebuild it).

    :raises ValueError: a network this format cannot describe
    """
    if isinstance(net, TabularSFNetwork):
        return {"kind": "tabular"}
    if isinstance(net, SFNetwork):
        if type(net.features_extractor) is not FlattenExtractor or net.activation_fn.__name__ not in _ACTIVATIONS:
            raise ValueError(
                "the policy-set format stores MLP SF networks with FlattenExtractor and a standard activation "
                f"({sorted(_ACTIVATIONS)}), got {type(net.features_extractor).__name__} / {net.activation_fn.__name__}"
            )
        return {
            "kind": "mlp",
            "net_arch": list(net.net_arch),
            "activation_fn": net.activation_fn.__name__,
            "normalize_images": bool(net.normalize_images),
        }
    raise ValueError(f"not an SF network: {type(net).__name__}")


def build_network(
    spec: dict[str, Any], observation_space: spaces.Space, action_space: spaces.Discrete, reward_dim: int
) -> nn.Module:
    """
    A fresh SF network from :func:`network_spec` data.

    :raises ValueError: unknown kind or activation
    """
    if spec.get("kind") == "tabular":
        return TabularSFNetwork(observation_space, action_space, reward_dim)
    if spec.get("kind") == "mlp":
        if spec.get("activation_fn") not in _ACTIVATIONS:
            known = sorted(_ACTIVATIONS)
            raise ValueError(f"unknown activation {spec.get('activation_fn')!r}, expected one of {known}")
        extractor = FlattenExtractor(observation_space)
        return SFNetwork(
            observation_space,
            action_space,
            extractor,
            extractor.features_dim,
            reward_dim,
            net_arch=[int(n) for n in spec["net_arch"]],
            activation_fn=_ACTIVATIONS[spec["activation_fn"]],
            normalize_images=bool(spec.get("normalize_images", True)),
        )
    raise ValueError(f"unknown network kind {spec.get('kind')!r}")


class GPIPolicy:
    """
    A set of successor-feature policies acting by generalized policy improvement.

    :param models: SFDQN models to put in the set (their current networks are copied)
    :param device: where the networks live, resolved when the first one is added (see
        :func:`~sb3_sfgpi.common.device.resolve_device`): ``"auto"`` keeps tables on the CPU and puts MLPs on
        CUDA where available. The default is the CPU: GPI acts one decision at a time, faster there.
    """

    def __init__(self, models: Iterable[SFDQN] = (), device: th.device | str = "cpu"):
        self._device_request = device
        self._device: th.device | None = None
        self.networks: list[nn.Module] = []
        self.infos: list[PolicyInfo] = []
        self._stacked: _StackedTables | _StackedMLP | _StackedVmap | None = None
        self._weights_cache: tuple[Any, tuple[np.ndarray, th.Tensor, np.ndarray]] | None = None
        for model in models:
            self.add(model)

    def __len__(self) -> int:
        return len(self.networks)

    @property
    def device(self) -> th.device:
        """Where the networks live (an empty set: where MLPs would go)."""
        return resolve_device(self._device_request) if self._device is None else self._device

    def to(self, device: th.device | str) -> GPIPolicy:
        """
        Move the set to another device (resolved as in the constructor).

        :return: the set itself
        :raises ValueError: a tabular set on a device other than the CPU
        """
        if self.networks:
            self._device = resolve_device(device, tabular=isinstance(self.networks[0], TabularSFNetwork))
            for net in self.networks:
                net.to(self._device)
        self._device_request = device
        self._stacked = None
        self._weights_cache = None
        return self

    @property
    def reward_dim(self) -> int:
        return self._first().reward_dim

    @property
    def observation_space(self) -> spaces.Space:
        return self._first().observation_space

    @property
    def action_space(self) -> spaces.Discrete:
        return self._first().action_space

    def _first(self) -> Any:
        if not self.networks:
            raise ValueError("the policy set is empty")
        return self.networks[0]

    def add(
        self,
        model: SFDQN | nn.Module,
        weights: np.ndarray | list[float] | None = None,
        value: np.ndarray | list[float] | None = None,
        agent: str | None = None,
        iteration: int | None = None,
    ) -> int:
        """
        Add a copy of a policy's SF network to the set.

        :param model: an SFDQN model, or an SF network (then ``weights`` is required)
        :param weights: the weights it was trained for (default: the model's)
        :param value: its value vector ``V^π``
        :param agent: the agent that learned it
        :param iteration: the OLS iteration that produced it
        :return: its index in the set
        :raises ValueError: a network of another architecture, spaces or reward dimension than the set's
        """
        if isinstance(model, SFDQN):
            net, weights = model.policy.sf_net, model.weights if weights is None else weights
        elif weights is None:
            raise ValueError("weights are required when adding a bare SF network")
        else:
            net = model
        spec = network_spec(net)
        if self.networks:
            first = self.networks[0]
            same = (
                spec == network_spec(first)
                and net.observation_space == first.observation_space
                and net.action_space == first.action_space
                and net.reward_dim == first.reward_dim
            )
            if not same:
                raise ValueError("all policies of a set must share network architecture, spaces and reward_dim")
        reward_dim = net.reward_dim
        w = validate_weights(weights, reward_dim)
        v = None if value is None else np.asarray(value, dtype=np.float64).reshape(reward_dim)
        if self._device is None:
            self._device = resolve_device(self._device_request, tabular=isinstance(net, TabularSFNetwork))
        copied = copy.deepcopy(net).to(self._device)
        copied.set_training_mode(False)
        for parameter in copied.parameters():
            parameter.requires_grad_(False)
        self.networks.append(copied)
        self.infos.append(PolicyInfo(w, v, agent, iteration))
        self._stacked = None
        self._weights_cache = None
        return len(self.networks) - 1

    def _stack(self) -> _StackedTables | _StackedMLP | _StackedVmap:
        if self._stacked is None:
            first = self.networks[0]
            if isinstance(first, TabularSFNetwork):
                self._stacked = _StackedTables(self.networks)  # type: ignore[arg-type]
            elif _StackedMLP.supports(first):
                self._stacked = _StackedMLP(self.networks)  # type: ignore[arg-type]
            else:
                self._stacked = _StackedVmap(self.networks)
        return self._stacked

    def _psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        """``ψ`` of every policy, shape ``(n_policies, batch, n_actions, d)``, in one batched pass."""
        with th.no_grad():
            return self._stack().psi(obs_tensor)

    def _psi_vmap(self, obs_tensor: th.Tensor) -> th.Tensor:
        """``ψ`` by the generic ``vmap`` path, whatever the kind of network (a reference for tests and benchmarks)."""
        with th.no_grad():
            return _StackedVmap(self.networks).psi(obs_tensor)

    def _obs_to_tensor(self, observation: np.ndarray) -> tuple[th.Tensor, bool]:
        return self._first().obs_to_tensor(observation)

    def _obs_to_array(self, observation: np.ndarray) -> tuple[np.ndarray, bool]:
        """The observation as a batch array and whether it was one (as SB3's ``obs_to_tensor``, without torch)."""
        space = self.observation_space
        if isinstance(observation, dict) or is_image_space(space):
            obs_tensor, vectorized = self._obs_to_tensor(observation)
            return obs_tensor.cpu().numpy(), vectorized
        array = np.asarray(observation)
        vectorized = is_vectorized_observation(array, space)
        return array.reshape((-1, *space.shape)), vectorized  # type: ignore[misc]

    def _validated_weights(self, w: np.ndarray | list[float]) -> tuple[np.ndarray, th.Tensor, np.ndarray]:
        """
        ``w`` checked and normalised: float64 array, float32 tensor on the set's device, float32 array.

        The last weights are remembered, so acting many times for one ``w`` validates it once.
        """
        try:
            raw = np.asarray(w, dtype=np.float64)
        except (TypeError, ValueError):
            raw = None
        key = None if raw is None else (raw.shape, raw.tobytes())
        cached = self._weights_cache
        if key is not None and cached is not None and cached[0] == key:
            return cached[1]
        weights = validate_weights(w if raw is None else raw, self.reward_dim)
        # float32 like the networks: Q = ψ · w is computed in single precision on every path.
        result = (weights, th.as_tensor(weights, dtype=th.float32, device=self.device), weights.astype(np.float32))
        self._weights_cache = (key, result)
        return result

    def successor_features(self, observation: np.ndarray) -> np.ndarray:
        """
        ``ψ^π(s, ·)`` of every policy in the set.

        :param observation: one observation or a batch
        :return: shape ``(n_policies, batch, n_actions, d)``
        """
        obs_tensor, _ = self._obs_to_tensor(observation)
        return self._psi(obs_tensor).cpu().numpy()

    def q_values(self, observation: np.ndarray, w: np.ndarray | list[float]) -> np.ndarray:
        """
        GPI action values ``max_π w · ψ^π(s, a)``.

        :param observation: one observation or a batch
        :param w: preference weights of length ``d``
        :return: shape ``(batch, n_actions)``
        """
        weights = self._validated_weights(w)
        obs, _ = self._obs_to_array(observation)
        return self._gpi_q(obs, weights)

    def _gpi_q(self, obs: np.ndarray, weights: tuple[np.ndarray, th.Tensor, np.ndarray]) -> np.ndarray:
        stacked = self._stack()
        if isinstance(stacked, _StackedTables) and self.device.type == "cpu":
            return stacked.q_values_numpy(obs, weights[2])
        obs_tensor = th.as_tensor(obs, device=self.device)
        with th.no_grad():
            return th.amax(stacked.psi(obs_tensor) @ weights[1], dim=0).cpu().numpy()

    def predict(
        self,
        observation: np.ndarray,
        w: np.ndarray | list[float],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        GPI action ``argmax_a max_π w · ψ^π(s, a)`` (ties go to the first action), as SB3's ``predict``.

        :param observation: one observation or a batch
        :param w: preference weights of length ``d``
        :param state: unused, returned as is
        :param episode_start: unused
        :param deterministic: GPI is deterministic; kept for SB3 compatibility
        :return: the actions (a scalar array for one observation) and ``state``
        :raises ValueError: bad weights or an empty set
        """
        weights = self._validated_weights(w)
        obs, vectorized = self._obs_to_array(observation)
        actions = self._gpi_q(obs, weights).argmax(axis=1)
        return (actions if vectorized else actions[0]), state

    def save(self, path: str | Path) -> None:
        """
        Write the set as a policy-set directory (see the module docstring).

        :param path: the directory (created if needed)
        """
        directory = Path(path)
        directory.mkdir(parents=True, exist_ok=True)
        entries = []
        for i, (net, info) in enumerate(zip(self.networks, self.infos, strict=True)):
            file = f"policy_{i:03d}.pt"
            # Each file is replaced atomically too: an interrupted save leaves the previous set loadable.
            buffer = io.BytesIO()
            th.save(_file_state(net), buffer)
            atomic_write_bytes(directory / file, buffer.getvalue())
            entries.append(info.to_dict(file))
        first = self._first()
        atomic_write_json(
            directory / MANIFEST,
            {
                "format": FORMAT,
                "version": VERSION,
                "reward_dim": int(first.reward_dim),
                "observation_space": space_to_dict(first.observation_space),
                "action_space": space_to_dict(first.action_space),
                "network": network_spec(first),
                "policies": entries,
            },
        )

    @classmethod
    def load(cls, path: str | Path, device: th.device | str = "cpu") -> GPIPolicy:
        """
        Read a policy-set directory written by :meth:`save`.

        :param path: the directory
        :param device: where to put the networks, as in the constructor; the files are read on the CPU, so a set
            saved on one device loads on any other
        :raises CorruptPolicySetError: a missing, truncated, inconsistent or foreign directory
        :raises ValueError: a tabular set on a device other than the CPU
        """
        directory = Path(path)
        try:
            manifest = read_json(directory / MANIFEST, "policy-set manifest")
            if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
                raise ValueError(f"{directory / MANIFEST} is not an sb3-sfgpi policy-set manifest")
            if manifest.get("version") != VERSION:
                raise ValueError(f"unsupported policy-set version {manifest.get('version')!r} (expected {VERSION})")
            reward_dim = int(manifest["reward_dim"])
            observation_space = space_from_dict(manifest["observation_space"])
            action_space = space_from_dict(manifest["action_space"])
            if not isinstance(action_space, spaces.Discrete):
                raise ValueError(f"the action space must be Discrete, got {action_space}")
            policy_set = cls(device="cpu")
            for entry in manifest["policies"]:
                net = build_network(manifest["network"], observation_space, action_space, reward_dim)
                net.load_state_dict(_network_state(net, _read_state_dict(directory, entry["file"])))
                policy_set.add(
                    net,
                    weights=entry["weights"],
                    value=entry.get("value"),
                    agent=entry.get("agent"),
                    iteration=entry.get("iteration"),
                )
        except CorruptPolicySetError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            raise CorruptPolicySetError(f"cannot load the policy set in {directory}: {error}") from error
        return policy_set.to(device)


class _StackedTables:
    """
    The tables of a tabular set, stacked state-major: row ``k`` holds ``ψ^π(s, ·)`` of every policy ``π`` for the
    ``k``-th state that some policy has learned (a non-zero row), and one last row of zeros serves every other state.

    Tables of large observation spaces are mostly zero (the Four-Room with object flags: under 1% of the rows), so
    the stack holds the learned rows only. ``ψ`` of a batch is one gather of its rows (``P·A·d`` contiguous floats
    per observation).
    """

    def __init__(self, networks: list[TabularSFNetwork]):
        first = networks[0]
        self.n_policies, self.n_actions, self.reward_dim = len(networks), first.n_actions, first.reward_dim
        self.n_states = first.table.num_embeddings
        self.state_index = first.state_index
        self.low = first.low.cpu().numpy()
        self.strides = first.strides.cpu().numpy()
        with th.no_grad():
            learned = th.stack([net.table.weight.any(dim=1) for net in networks]).any(dim=0).nonzero().flatten()
            self.stack_row = th.full((self.n_states,), len(learned), dtype=th.long, device=learned.device)
            self.stack_row[learned] = th.arange(len(learned), device=learned.device)
            width = self.n_policies * self.n_actions * self.reward_dim
            rows = th.stack([net.table.weight[learned] for net in networks], dim=1).reshape(len(learned), width)
            self.tables = th.cat([rows, rows.new_zeros(1, rows.shape[1])])
        cpu = self.tables.device.type == "cpu"
        self.tables_numpy = self.tables.numpy() if cpu else None
        self.stack_row_numpy = self.stack_row.numpy() if cpu else None

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        rows = self.tables.index_select(0, self.stack_row[self.state_index(obs_tensor)])
        return rows.view(-1, self.n_policies, self.n_actions, self.reward_dim).transpose(0, 1)

    def q_values_numpy(self, obs: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """GPI action values of a batch, in numpy (CPU sets): cheaper than torch for a few small operations."""
        assert self.tables_numpy is not None
        index = ((obs.astype(np.int64).reshape(obs.shape[0], -1) - self.low) * self.strides).sum(axis=1)
        if index.size and (index.min() < 0 or index.max() >= self.n_states):
            raise IndexError(f"observation outside the table ({self.n_states} rows): {obs.tolist()}")
        rows = self.tables_numpy.take(self.stack_row_numpy.take(index), axis=0).reshape(-1, self.reward_dim)
        return (rows @ weights).reshape(-1, self.n_policies, self.n_actions).max(axis=1)


class _StackedMLP:
    """
    MLP SF networks stacked layer by layer: weights ``(P, in, out)``, biases ``(P, 1, out)``.

    The features extractor has no parameters, so the features are computed once and shared; each ``Linear``
    of the ``P`` networks is then one ``baddbmm``.
    """

    def __init__(self, networks: list[SFNetwork]):
        first = networks[0]
        self.first = first
        self.n_policies, self.n_actions, self.reward_dim = len(networks), first.n_actions, first.reward_dim
        self.layers: list[tuple[th.Tensor, th.Tensor] | nn.Module] = []
        with th.no_grad():
            for i, module in enumerate(first.sf_net):
                if isinstance(module, nn.Linear):
                    linears = [net.sf_net[i] for net in networks]
                    weight = th.stack([lin.weight.transpose(0, 1) for lin in linears]).contiguous()
                    bias = th.stack([lin.bias for lin in linears]).unsqueeze(1)
                    self.layers.append((weight, bias))
                else:
                    self.layers.append(module)

    @staticmethod
    def supports(net: nn.Module) -> bool:
        """An MLP SF network whose features extractor holds no state and whose layers are Linear or activations."""
        if not isinstance(net, SFNetwork) or not isinstance(net.sf_net, nn.Sequential):
            return False
        extractor = net.features_extractor
        if any(True for _ in extractor.parameters()) or any(True for _ in extractor.buffers()):
            return False
        allowed = tuple(_ACTIVATIONS.values())
        for module in net.sf_net:
            if isinstance(module, nn.Linear):
                if module.bias is None:
                    return False
            elif type(module) not in allowed:
                return False
        return True

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        features = self.first.extract_features(obs_tensor, self.first.features_extractor)
        n_policies = self.n_policies
        x = features.unsqueeze(0).expand(n_policies, *features.shape)
        for layer in self.layers:
            if isinstance(layer, tuple):
                x = th.baddbmm(layer[1], x, layer[0])
            else:
                x = layer(x)
        return x.view(n_policies, -1, self.n_actions, self.reward_dim)


class _StackedVmap:
    """Any networks of one architecture: ``stack_module_state`` + ``vmap`` over ``functional_call``."""

    def __init__(self, networks: list[nn.Module]):
        self.params, self.buffers = stack_module_state(networks)  # type: ignore[arg-type]
        self.skeleton = copy.deepcopy(networks[0]).to("meta")

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        skeleton = self.skeleton

        def one(p: dict[str, th.Tensor], b: dict[str, th.Tensor], x: th.Tensor) -> th.Tensor:
            return functional_call(skeleton, (p, b), (x,))

        return th.vmap(one, in_dims=(0, 0, None))(self.params, self.buffers, obs_tensor)


def _read_state_dict(directory: Path, file: str) -> dict[str, th.Tensor]:
    path = directory / file
    if Path(file).name != file or not path.is_file():
        raise CorruptPolicySetError(f"policy file {file!r} listed in {directory / MANIFEST} is missing")
    try:
        state = th.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for truncated files and refused pickles
        raise CorruptPolicySetError(f"policy file {path} is unreadable or unsafe: {error}") from error
    if not isinstance(state, dict) or not all(isinstance(v, th.Tensor) for v in state.values()):
        raise CorruptPolicySetError(f"policy file {path} does not hold a state dict of tensors")
    return state


def _file_state(net: nn.Module) -> dict[str, th.Tensor]:
    """What a policy file holds: the network's state dict, a table's only by its non-zero rows (most stay zero)."""
    state = {key: value.detach().cpu() for key, value in net.state_dict().items()}
    if isinstance(net, TabularSFNetwork):
        table = state.pop("table.weight")
        rows = table.any(dim=1).nonzero().flatten()
        state.update({"table.rows": rows, "table.values": table[rows], "table.shape": th.tensor(table.shape)})
    return state


def _network_state(net: nn.Module, state: dict[str, th.Tensor]) -> dict[str, th.Tensor]:
    """The state dict of ``net`` from what a policy file holds (the inverse of :func:`_file_state`)."""
    if not isinstance(net, TabularSFNetwork) or "table.weight" in state:
        return state
    state = dict(state)
    rows, values, shape = state.pop("table.rows"), state.pop("table.values"), state.pop("table.shape")
    expected = net.table.weight.shape
    if tuple(shape.tolist()) != tuple(expected):
        raise ValueError(f"the stored table has shape {tuple(shape.tolist())}, the network's is {tuple(expected)}")
    if rows.dtype != th.long or rows.ndim != 1 or values.shape != (len(rows), expected[1]):
        raise ValueError(f"stored table rows {tuple(rows.shape)} and values {tuple(values.shape)} do not match")
    if len(rows) and (rows.min() < 0 or rows.max() >= expected[0]):
        raise ValueError(f"stored table rows outside 0..{expected[0] - 1}")
    table = th.zeros(expected, dtype=values.dtype)
    table[rows] = values
    return {**state, "table.weight": table}
