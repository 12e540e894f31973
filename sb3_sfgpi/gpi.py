"""Generalized policy improvement over a set of successor-feature policies.

``π(s) = argmax_a max_{π ∈ Π} w · ψ^π(s, a)``: any preference ``w`` gets a behaviour from the set,
without training. All networks of a set share one architecture, so GPI evaluates them in a single batched
pass (:mod:`sb3_sfgpi.gpi_decisions`). A set also selects its sub-sets: the policies whose values form its CCS,
the policies one agent learned, and the joint policy of agents acting by GPI.

Policy-set directory format (``GPIPolicy.save`` / ``GPIPolicy.load``)::

    manifest.json     {"format": "sb3-sfgpi/policy-set", "version": 1, "reward_dim": d,
                       "observation_space": {...}, "action_space": {...}, "network": {...},
                       "policies": [{"file": "policy_000.pt", "weights": [...], "value": [...] | null,
                                     "agent": str | null, "iteration": int | null,
                                     "retired": int | null}, ...]}
    policy_000.pt     one SF network's tensors (:mod:`sb3_sfgpi.policy_files`)

A run's directory also keeps the policies that validation retired from Π (``retired``: the iteration after which
they left), so that a resumed run restores Π exactly; :meth:`GPIPolicy.load` leaves them out unless asked.

The manifest is written last and atomically, so a directory whose save was interrupted keeps the
previous manifest or has none. Loading never runs code from the directory.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch as th
from torch import nn

from sb3_sfgpi.common.device import resolve_device
from sb3_sfgpi.common.rollouts import JointPolicy
from sb3_sfgpi.common.weights import validate_weights
from sb3_sfgpi.gpi_decisions import BatchedGPI
from sb3_sfgpi.gpi_predictor import GPIPredictor
from sb3_sfgpi.ols import OLS, TOLERANCE
from sb3_sfgpi.policy_files import CorruptPolicySetError, file_state, network_spec
from sb3_sfgpi.policy_set_files import MANIFEST, PolicyInfo, read_policy_set, write_policy_set
from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork
from sb3_sfgpi.sfdqn.sfdqn import SFDQN
from sb3_sfgpi.stacking import LeaveOneOut, StackedTables
from sb3_sfgpi.tabular.network import TabularSFNetwork

__all__ = ["MANIFEST", "CorruptPolicySetError", "Decisions", "GPIPolicy", "GPIPredictor", "PolicyInfo"]


class Decisions(NamedTuple):
    """One joint decision of agents acting by GPI (:meth:`GPIPolicy.joint_policy`'s ``trace``)."""

    #: the agents' observations, stacked
    observations: np.ndarray
    #: their action masks, or None where the env gives none
    masks: np.ndarray | None
    #: GPI's actions
    actions: np.ndarray
    #: per agent, the members that attained GPI's value of its action (:meth:`GPIPolicy.predict_followed`)
    followed: list[frozenset[int]]


class GPIPolicy(BatchedGPI):
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
        self.networks_changed()
        return self

    def add(
        self,
        model: SFDQN | nn.Module,
        weights: np.ndarray | list[float] | None = None,
        value: np.ndarray | list[float] | None = None,
        agent: str | None = None,
        iteration: int | None = None,
        retired: int | None = None,
    ) -> int:
        """
        Add a copy of a policy's SF network to the set (a network conditioned on the weights: bound to ``weights``,
        see :meth:`~sb3_sfgpi.sfdqn.conditioned.ConditionedSFNetwork.bound_to`).

        :param model: an SFDQN model, or an SF network (then ``weights`` is required)
        :param weights: the weights it was trained for (default: the model's)
        :param value: its value vector ``V^π``
        :param agent: the agent that learned it
        :param iteration: the OLS iteration that produced it
        :param retired: the iteration after which validation took it out of Π (a run's record of Π only)
        :return: its index in the set
        :raises ValueError: a network of another architecture, spaces or reward dimension than the set's
        """
        if isinstance(model, SFDQN):
            net, weights = model.policy.member_net, model.weights if weights is None else weights
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
        copied = (net.bound_to(w) if isinstance(net, ConditionedSFNetwork) else copy.deepcopy(net)).to(self._device)
        copied.set_training_mode(False)
        for parameter in copied.parameters():
            parameter.requires_grad_(False)
        stacked = self._stacked
        self.networks.append(copied)
        self.infos.append(PolicyInfo(w, v, agent, iteration, retired))
        self.networks_changed()
        if isinstance(stacked, StackedTables):  # a table joins the stack, nothing stacked again
            self._stacked = stacked.with_table(copied)
        return len(self.networks) - 1

    def pop(self) -> PolicyInfo:
        """
        Remove the policy added last.

        :return: its info
        :raises ValueError: the set is empty
        """
        self._first()
        stacked = self._stacked
        self.networks.pop()
        self.networks_changed()
        if isinstance(stacked, StackedTables) and self.networks:
            self._stacked = stacked.without_last()
        return self.infos.pop()

    def retire(self, index: int, iteration: int | None) -> None:
        """
        Mark the policy at ``index`` as taken out of Π after ``iteration`` (``None``: back in Π). Only a run's
        record of Π holds retired policies; :meth:`members` is the set GPI acts over.
        """
        self.infos[index] = replace(self.infos[index], retired=iteration)

    # --- selections ---------------------------------------------------------------------------------------
    def subset(self, indices: Iterable[int]) -> GPIPolicy:
        """A new set holding copies of the policies at ``indices``, in that order, with their infos."""
        subset, indices = GPIPolicy(device=self.device), list(indices)
        for i in indices:
            info = self.infos[i]
            subset.add(self.networks[i], info.weights, info.value, info.agent, info.iteration, info.retired)
        if isinstance(self._stacked, StackedTables) and indices:  # the tables' columns of this set's stack
            subset._stacked = self._stacked.columns(indices)
        return subset

    def without(self, member: int) -> GPIPolicy:
        """
        A view of the set without the policy at ``member``: it shares this set's networks and batched copy (nothing
        is copied, nothing is stacked again), so it acts as :meth:`subset` would, for as long as this set is unchanged.
        For scoring leave-one-out sets (:class:`~sb3_sfgpi.validation.ValidationScorer`); to keep or change, use
        :meth:`subset`.

        :raises IndexError: no policy at ``member``
        """
        if not 0 <= member < len(self):
            raise IndexError(f"no policy {member} in a set of {len(self)}")
        view = GPIPolicy(device=self.device)
        view.networks = [net for i, net in enumerate(self.networks) if i != member]
        view.infos = [info for i, info in enumerate(self.infos) if i != member]
        view._device, view._stacked = self.device, LeaveOneOut(self._stack(), member)
        return view

    def members(self) -> GPIPolicy:
        """The policies not retired (see :meth:`retire`), in their order: Π, as GPI acts over it."""
        return self.subset(i for i, info in enumerate(self.infos) if info.retired is None)

    def as_of(self, iteration: int) -> GPIPolicy:
        """
        A run's record as it was after ``iteration``: the policies of iterations up to it (and those without one),
        the retirements that came later undone.
        """
        record = self.subset(
            i for i, info in enumerate(self.infos) if info.iteration is None or info.iteration <= iteration
        )
        for i, info in enumerate(record.infos):
            if info.retired is not None and info.retired > iteration:
                record.retire(i, None)
        return record

    def agent_policies(self, agent: str) -> GPIPolicy:
        """
        The policies ``agent`` learned itself (e.g. the set of an a priori scalarised learner).

        :raises ValueError: the agent has no policy in the set
        """
        indices = [i for i, info in enumerate(self.infos) if info.agent == agent]
        if not indices:
            raise ValueError(f"the policy set has no policy learned by agent {agent!r}")
        return self.subset(indices)

    def ccs_policies(self, tolerance: float = TOLERANCE) -> GPIPolicy:
        """
        The policies whose value vectors ``V^π`` form the set's convex coverage set (CCS): those that are the best
        of the set, by more than ``tolerance``, for some weight (by :class:`~sb3_sfgpi.ols.OLS` over the stored
        values; of policies with the same value the first is kept). GPI over them ignores dominated policies,
        whose learned SFs can only mislead it where they overestimate.

        :return: a new set holding the CCS policies, in their order in this set
        :raises ValueError: no policy of the set has a value
        """
        with_values = [i for i, info in enumerate(self.infos) if info.value is not None]
        if not with_values:
            raise ValueError("the policies of the set carry no value vectors: their CCS is unknown")
        ols = OLS(self.reward_dim, tolerance=tolerance)
        for i in with_values:
            ols.add_solution(self.infos[i].value, self.infos[i].weights)
        kept: list[int] = []
        for i in with_values:
            value = np.asarray(self.infos[i].value)
            in_ccs = any(np.max(np.abs(value - v)) <= tolerance for v in ols.ccs)
            if in_ccs and not any(np.max(np.abs(value - self.infos[j].value)) <= tolerance for j in kept):
                kept.append(i)
        return self.subset(kept)

    def joint_policy(
        self,
        w: np.ndarray | Sequence[float],
        agents: Sequence[str] | None = None,
        trace: list[Decisions] | None = None,
    ) -> JointPolicy:
        """
        The joint policy of agents acting by GPI for the preference ``w``.

        :param w: preference weights
        :param agents: None: every agent acts by GPI over the whole set (one batched call per step); the agents'
            names: each of them acts by GPI over the policies it learned itself (:meth:`agent_policies`)
        :param trace: where given (``agents`` None), every decision appends to it the agents' observations, their
            action masks (None without), their actions and the members GPI followed for each
            (:meth:`predict_followed`); the actions are the same
        :raises ValueError: bad weights; an agent without policies in the set; ``trace`` with ``agents``
        """
        self._validated_weights(w)
        if trace is not None and agents is not None:
            raise ValueError("decisions are traced where every agent acts by GPI over the whole set")
        own = None if agents is None else {agent: self.agent_policies(agent) for agent in agents}

        def act(observations: dict[str, Any], action_masks: Mapping[str, Any] | None = None) -> dict[str, int]:
            names = list(observations)
            masks = None if action_masks is None else np.stack([action_masks[a] for a in names])
            if own is None:
                batch = np.stack([observations[a] for a in names])
                if trace is None:
                    actions, _ = self.predict(batch, w, action_masks=masks)
                else:
                    actions, members = self.predict_followed(batch, w, masks)
                    trace.append(Decisions(batch, masks, actions, members))
                return dict(zip(names, actions.tolist(), strict=True))
            return {
                a: int(own[a].predict(observations[a], w, action_masks=None if masks is None else masks[i])[0])
                for i, a in enumerate(names)
            }

        return act

    def for_weights(self, w: np.ndarray | Sequence[float]) -> GPIPredictor:
        """
        GPI for the preference ``w`` behind SB3's ``predict(observation, state, episode_start, deterministic)``, which
        SB3's tools (``evaluate_policy`` on ``LinearReward(env, weight=w)``, RL-Zoo-style scripts) call without a
        weight. It acts over this set as it is when it acts.

        :raises ValueError: bad weights or an empty set
        """
        return GPIPredictor(self, w)

    def save(self, path: str | Path, manifest: str = MANIFEST, stamp: int | None = None) -> None:
        """
        Write the set as a policy-set directory (see the module docstring).

        :param path: the directory (created if needed)
        :param manifest: the manifest's file name (a run directory stages a set under another name until its
            checkpoint commits it)
        :param stamp: a number in every policy file's name (``policy_000.0002.pt``), so that a set whose manifest
            names other files is not written over
        """
        self._check_saveable()
        suffix = "" if stamp is None else f".{stamp:04d}"
        entries = [info.to_dict(f"policy_{i:03d}{suffix}.pt") for i, info in enumerate(self.infos)]
        write_policy_set(Path(path), self.networks, entries, self._first(), manifest)

    def _check_saveable(self) -> None:
        """Refuse to save what :meth:`load` would refuse: non-finite SFs, values or weights, or an empty set."""
        self._first()
        for index, (net, info) in enumerate(zip(self.networks, self.infos, strict=True)):
            name = f"policy {index} (agent {info.agent!r}, iteration {info.iteration})"
            for key, value in file_state(net).items():
                if value.is_floating_point() and not bool(th.isfinite(value).all()):
                    raise ValueError(f"cannot save {name}: its network holds NaN or inf in {key!r}")
            for what, array in (("value", info.value), ("weights", info.weights)):
                if array is not None and not np.isfinite(np.asarray(array, dtype=np.float64)).all():
                    raise ValueError(f"cannot save {name}: its {what} is not finite")

    @classmethod
    def load(cls, path: str | Path, device: th.device | str = "cpu", retired: bool = False) -> GPIPolicy:
        """
        Read a policy-set directory written by :meth:`save`.

        :param path: the directory, or a manifest file in it
        :param device: where to put the networks, as in the constructor; the files are read on the CPU, so a set
            saved on one device loads on any other
        :param retired: also the policies that validation retired from Π (a run's whole record, to resume it);
            default: Π's members only
        :raises CorruptPolicySetError: a missing, truncated, inconsistent or foreign directory
        :raises ValueError: a tabular set on a device other than the CPU
        """
        policy_set = cls(device="cpu")
        try:
            for net, entry in read_policy_set(Path(path), retired):
                policy_set.add(
                    net,
                    weights=entry["weights"],
                    value=entry.get("value"),
                    agent=entry.get("agent"),
                    iteration=entry.get("iteration"),
                    retired=entry.get("retired"),
                )
        except CorruptPolicySetError:
            raise
        except (KeyError, TypeError, ValueError, RuntimeError) as error:
            raise CorruptPolicySetError(f"cannot load the policy set in {path}: {error}") from error
        return policy_set.to(device)
