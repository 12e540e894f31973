"""A policy-set directory: ``manifest.json`` and one tensors-only file per policy, written and read back checked.

The manifest holds the format and version, the objectives' number, the spaces, the network architecture and one
entry per policy (its file, weights, value, agent, iteration, and when validation retired it). Every file is
replaced atomically, so an interrupted save leaves the previous set loadable. Reading never runs code: paths stay
inside the directory, shapes and values are checked, and a set that would need more than half of the machine's
memory is refused before anything is allocated.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from torch import nn

from sb3_sfgpi.common.serialization import (
    atomic_write_bytes,
    atomic_write_json,
    read_json,
    space_from_dict,
    space_to_dict,
)
from sb3_sfgpi.policy_files import (
    CorruptPolicySetError,
    build_network,
    declared_bytes,
    file_state,
    memory_budget,
    network_spec,
    read_state_dict,
)
from sb3_sfgpi.run_directory import MANIFEST  # plain data: the name a run directory looks for too
from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork

FORMAT = "sb3-sfgpi/policy-set"
VERSION = 1


@dataclass(frozen=True)
class PolicyInfo:
    """
    What the set knows of one policy besides its network.

    :param weights: the preference weights it was trained for
    :param value: its value vector ``V^π`` (``None`` if not evaluated)
    :param agent: the agent that learned it
    :param iteration: the OLS iteration that produced it
    :param retired: the iteration after which policy validation took it out of Π (``None``: in Π)
    """

    weights: np.ndarray
    value: np.ndarray | None = None
    agent: str | None = None
    iteration: int | None = None
    retired: int | None = None

    def to_dict(self, file: str) -> dict[str, Any]:
        return {
            "file": file,
            "weights": self.weights.tolist(),
            "value": None if self.value is None else self.value.tolist(),
            "agent": self.agent,
            "iteration": self.iteration,
            "retired": self.retired,
        }


def write_policy_set(
    directory: Path,
    networks: Sequence[nn.Module],
    entries: Sequence[dict[str, Any]],
    first: Any,
    manifest: str = MANIFEST,
) -> None:
    """
    Write the policy files, then the manifest.

    :param networks: the SF networks, one per policy
    :param entries: the manifest's entry of each (``"file"`` names its file)
    :param first: the first policy's network (its spaces, objectives and architecture describe the set)
    :param manifest: the manifest's file name
    """
    directory.mkdir(parents=True, exist_ok=True)
    for net, entry in zip(networks, entries, strict=True):
        buffer = io.BytesIO()
        th.save(file_state(net), buffer)
        atomic_write_bytes(directory / entry["file"], buffer.getvalue())
    atomic_write_json(
        directory / manifest,
        {
            "format": FORMAT,
            "version": VERSION,
            "reward_dim": int(first.reward_dim),
            "observation_space": space_to_dict(first.observation_space),
            "action_space": space_to_dict(first.action_space),
            "network": network_spec(first),
            "policies": list(entries),
        },
    )


def manifest_path(path: Path) -> Path:
    """The manifest of a policy set given as its directory (its ``manifest.json``) or as a manifest file."""
    return path if path.is_file() else path / MANIFEST


def read_policy_set(path: Path, retired: bool) -> list[tuple[nn.Module, dict[str, Any]]]:
    """
    The networks of a policy set with their manifest entries, checked.

    :param path: the set's directory (its ``manifest.json``) or a manifest file (its policy files beside it)
    :param retired: also the policies that validation retired (default of the caller: Π's members only)
    :raises ~sb3_sfgpi.policy_files.CorruptPolicySetError: a missing, truncated, inconsistent or foreign directory
    """
    manifest_file = manifest_path(path)
    directory = manifest_file.parent
    try:
        manifest = _read_manifest(manifest_file)
        observation_space = space_from_dict(manifest["observation_space"])
        action_space = space_from_dict(manifest["action_space"])
        if not isinstance(action_space, spaces.Discrete):
            raise ValueError(f"the action space must be Discrete, got {action_space}")
        reward_dim = int(manifest["reward_dim"])
        files = [entry["file"] for entry in manifest["policies"]]
        if len(set(files)) != len(files):
            raise ValueError("the manifest lists a policy file more than once")
        network_bytes = declared_bytes(manifest["network"], observation_space, action_space, reward_dim)
        _check_memory(len(files), network_bytes)
        policies = []
        for entry in manifest["policies"]:
            if _checked_entry(entry) is not None and not retired:
                continue
            net = build_network(manifest["network"], observation_space, action_space, reward_dim)
            net.load_state_dict(read_state_dict(directory, entry["file"], 2 * network_bytes + 2**20))
            _check_bound(net, entry)
            policies.append((net, entry))
        return policies
    except CorruptPolicySetError:
        raise
    except (KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CorruptPolicySetError(f"cannot load the policy set in {directory}: {error}") from error


def _read_manifest(path: Path) -> dict[str, Any]:
    manifest = read_json(path, "policy-set manifest")
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError(f"{path} is not an sb3-sfgpi policy-set manifest")
    if type(manifest.get("version")) is not int or manifest["version"] != VERSION:  # not true, not 1.0
        raise ValueError(f"unsupported policy-set version {manifest.get('version')!r} (expected {VERSION})")
    if not isinstance(manifest["network"], dict) or not isinstance(manifest["policies"], list):
        raise ValueError("the manifest's 'network' must be an object and its 'policies' a list")
    return manifest


def _checked_entry(entry: dict[str, Any]) -> int | None:
    """Check a policy's entry, every field's type; return the iteration after which it was retired (None: in Π)."""
    if not isinstance(entry, dict) or not isinstance(entry.get("file"), str):
        raise ValueError(f"a policy entry must be an object with a 'file' name, got {entry!r}")
    for key in ("weights", "value"):
        numbers = entry.get(key)
        if (key == "weights" or numbers is not None) and not _finite_numbers(numbers):
            raise ValueError(f"the {key} of {entry['file']!r} must be a list of finite numbers, got {numbers!r}")
    iteration, agent = entry.get("iteration"), entry.get("agent")
    if iteration is not None and (type(iteration) is not int or iteration < 0):
        raise ValueError(f"'iteration' of {entry['file']!r} must be null or a non-negative integer, got {iteration!r}")
    if agent is not None and not isinstance(agent, str):
        raise ValueError(f"'agent' of {entry['file']!r} must be null or a name, got {agent!r}")
    left = entry.get("retired")
    if left is not None and (isinstance(left, bool) or not isinstance(left, int) or left < 1):
        raise ValueError(f"'retired' of {entry['file']!r} must be null or an iteration, got {left!r}")
    return left


def _finite_numbers(value: Any) -> bool:
    """Whether ``value`` is a JSON list of finite numbers (not bools, not strings)."""
    return (
        isinstance(value, list)
        and all(type(x) in (int, float) for x in value)
        and bool(np.isfinite(np.asarray(value, dtype=np.float64)).all())
    )


def _check_bound(net: nn.Module, entry: dict[str, Any]) -> None:
    """Refuse a conditioned network bound to other weights than its entry's: GPI would act for the wrong policy."""
    if isinstance(net, ConditionedSFNetwork):
        bound = net.member_weights.numpy().astype(np.float64)
        if not np.allclose(bound, np.asarray(entry["weights"], dtype=np.float64), atol=1e-6):
            raise ValueError(
                f"{entry['file']!r} is bound to the weights {bound.tolist()}, its entry says {entry['weights']}"
            )


def _check_memory(n_policies: int, network_bytes: int) -> None:
    """Refuse a manifest whose policies would take more than half of this machine's memory, before allocating."""
    budget = memory_budget()
    if budget is not None and n_policies * network_bytes > budget:
        raise ValueError(
            f"the manifest asks for {n_policies} policies of {network_bytes / 1e6:.1f} MB each "
            f"({n_policies * network_bytes / 1e9:.1f} GB), more than half of this machine's memory "
            f"({2 * budget / 1e9:.1f} GB)"
        )
