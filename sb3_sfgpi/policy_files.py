"""One SF network as plain data and tensors: its architecture (JSON) and what its policy file holds.

A policy file holds the network's state dict (tensors only, read with ``weights_only=True``); a table is stored as
its stored rows: ``"table.rows"`` (their indices), ``"table.values"`` (the rows), ``"table.shape"`` and, where it is
not zero, ``"table.default"`` (the value of every other row). Reading never runs code.
"""

from __future__ import annotations

import itertools
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.torch_layers import FlattenExtractor
from torch import nn

from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork
from sb3_sfgpi.sfdqn.networks import SFNetwork, non_finite_key
from sb3_sfgpi.tabular.network import TabularSFNetwork, observation_radices

_ACTIVATIONS = {name: getattr(nn, name) for name in ("ReLU", "Tanh", "ELU", "LeakyReLU", "GELU", "SiLU", "Identity")}


class CorruptPolicySetError(ValueError):
    """A policy-set directory that cannot be loaded: missing, truncated, inconsistent or foreign files."""


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
        spec = {
            "kind": "mlp",
            "net_arch": list(net.net_arch),
            "activation_fn": net.activation_fn.__name__,
            "normalize_images": bool(net.normalize_images),
        }
        if isinstance(net, ConditionedSFNetwork):
            spec.update(kind="conditioned-mlp", n_heads=net.n_heads)
        return spec
    raise ValueError(f"not an SF network: {type(net).__name__}")


#: The most heads a conditioned network of a policy set may have.
MAX_HEADS = 16

#: The MLP network classes by their kind in a network spec.
MLP_KINDS: dict[str, type[SFNetwork] | type[ConditionedSFNetwork]] = {
    "mlp": SFNetwork,
    "conditioned-mlp": ConditionedSFNetwork,
}


def build_network(
    spec: dict[str, Any], observation_space: spaces.Space, action_space: spaces.Discrete, reward_dim: int
) -> nn.Module:
    """
    A fresh SF network from :func:`network_spec` data.

    :raises ValueError: unknown kind or activation
    """
    if spec.get("kind") == "tabular":
        return TabularSFNetwork(observation_space, action_space, reward_dim)
    if spec.get("kind") in MLP_KINDS:
        if spec.get("activation_fn") not in _ACTIVATIONS:
            known = sorted(_ACTIVATIONS)
            raise ValueError(f"unknown activation {spec.get('activation_fn')!r}, expected one of {known}")
        extractor = FlattenExtractor(observation_space)
        heads = {"n_heads": _n_heads(spec)} if spec["kind"] == "conditioned-mlp" else {}
        return MLP_KINDS[spec["kind"]](
            observation_space,
            action_space,
            extractor,
            extractor.features_dim,
            reward_dim,
            net_arch=[int(n) for n in spec["net_arch"]],
            activation_fn=_ACTIVATIONS[spec["activation_fn"]],
            normalize_images=bool(spec.get("normalize_images", True)),
            **heads,
        )
    raise ValueError(f"unknown network kind {spec.get('kind')!r}")


def _n_heads(spec: dict[str, Any]) -> int:
    """The number of heads of a conditioned network's spec (1 where it says none).

    :raises ValueError: not a positive integer
    """
    n_heads = spec.get("n_heads", 1)
    if type(n_heads) is not int or not 1 <= n_heads <= MAX_HEADS:
        raise ValueError(f"n_heads must be an integer in [1, {MAX_HEADS}], got {n_heads!r}")
    return n_heads


def declared_bytes(
    spec: dict[str, Any], observation_space: spaces.Space, action_space: spaces.Discrete, reward_dim: int
) -> int:
    """
    The memory one network of :func:`network_spec` data takes (float32 parameters), computed before building it: for
    a table, the most it can take (every row stored).

    :raises ValueError: unknown kind, or a space a table cannot index
    """
    outputs = int(action_space.n) * reward_dim
    if spec.get("kind") == "tabular":
        _, n_values = observation_radices(observation_space)
        return int(np.prod(n_values.astype(np.float64))) * outputs * 4
    if spec.get("kind") in MLP_KINDS:
        sizes = [spaces.flatdim(observation_space), *[int(n) for n in spec["net_arch"]], outputs]
        linear = sum((n_in + 1) * n_out for n_in, n_out in itertools.pairwise(sizes))
        if spec["kind"] == "conditioned-mlp":  # per head: the weight's features, the layer norms; the member's weights
            hidden = [int(n) for n in spec["net_arch"]]
            linear += (reward_dim + 1) * hidden[0] + 2 * sum(hidden[1:])
            linear = linear * _n_heads(spec) + reward_dim
        return linear * 4
    raise ValueError(f"unknown network kind {spec.get('kind')!r}")


def memory_budget() -> int | None:
    """Half of this machine's physical memory in bytes (None where the system does not say)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (AttributeError, ValueError, OSError):
        return None


def read_state_dict(directory: Path, file: str, max_bytes: int | None = None) -> dict[str, th.Tensor]:
    """
    The tensors of a policy file, read without running code and checked finite in float32.

    :param max_bytes: the most its records may hold once decompressed (the network's declared size and some room):
        checked in the archive's directory before anything is decompressed
    :raises CorruptPolicySetError: a missing, linked-out, unreadable, oversized or non-finite file
    """
    path = directory / file
    if Path(file).name != file or not path.is_file():
        raise CorruptPolicySetError(f"policy file {file!r} listed in the manifest of {directory} is missing")
    if path.is_symlink() and path.resolve().parent != directory.resolve():
        raise CorruptPolicySetError(f"policy file {path} is a link that leaves the directory")
    if max_bytes is not None:
        _check_unpacked_size(path, max_bytes)
    try:
        state = th.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for truncated files and refused pickles
        raise CorruptPolicySetError(f"policy file {path} is unreadable or unsafe: {error}") from error
    if not isinstance(state, dict) or not all(isinstance(v, th.Tensor) for v in state.values()):
        raise CorruptPolicySetError(f"policy file {path} does not hold a state dict of tensors")
    key = non_finite_key(state)
    if key is not None:
        raise CorruptPolicySetError(f"policy file {path} holds non-finite values (NaN or inf) in {key!r}")
    return state


def _check_unpacked_size(path: Path, max_bytes: int) -> None:
    """Refuse a policy file (a zip archive) whose records would take more than ``max_bytes`` once decompressed."""
    try:
        with zipfile.ZipFile(path) as archive:
            unpacked = sum(info.file_size for info in archive.infolist())
    except (zipfile.BadZipFile, OSError):
        return  # not an archive: torch.load says what it is
    if unpacked > max_bytes:
        raise CorruptPolicySetError(
            f"policy file {path} unpacks to {unpacked / 1e6:.1f} MB, more than its network can hold "
            f"({max_bytes / 1e6:.1f} MB)"
        )


def file_state(net: nn.Module) -> dict[str, th.Tensor]:
    """What a policy file holds: the network's state dict (a table's holds its stored rows, see TabularSFNetwork)."""
    return {key: value.detach().cpu() for key, value in net.state_dict().items()}
