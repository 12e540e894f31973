"""The networks of a policy set evaluated in one batched pass: ``ψ`` of every policy, shape ``(P, batch, A, d)``.

* tables: one gather of the observed rows from a ``(S, P·A·d)`` stack of the tables' learned rows;
* MLPs (parameter-free features extractor, ``Linear`` layers and activations): the features are extracted once and
  every layer is one batched matrix product over the ``P`` networks;
* weight-conditioned networks (:class:`~sb3_sfgpi.sfdqn.conditioned.ConditionedSFNetwork`, each bound to its
  member's weights): the same, head by head, with layer normalisation as ``vmap`` computes it;
* anything else: ``torch.func.stack_module_state`` + ``vmap`` over ``functional_call``.

The specialised ones give ``vmap``'s ``ψ`` bit for bit and skip its per-call overhead (about a millisecond per
decision, more for conditioned networks, whose parameters ``functional_call`` swaps in and out; see
``benchmarks/bench_gpi.py``).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np
import torch as th
from torch import nn
from torch.func import functional_call, stack_module_state
from torch.nn import functional as F

from sb3_sfgpi.common.weights import weighted_sum
from sb3_sfgpi.policy_files import _ACTIVATIONS
from sb3_sfgpi.sfdqn.networks import SFNetwork
from sb3_sfgpi.tabular.network import TabularSFNetwork

if TYPE_CHECKING:
    from sb3_sfgpi.sfdqn.conditioned import ConditionedSFNetwork


class StackedTables:
    """
    The tables of a tabular set, stacked state-major: row ``k`` holds ``ψ^π(s, ·)`` of every policy ``π`` for the
    ``k``-th state that some policy has stored, and one last row holds every policy's default row, which serves every
    other state.

    Tables of large observation spaces are mostly never visited (the Four-Room with object flags visits a small
    fraction of its rows), so the stack holds the stored rows only. ``ψ`` of a batch is one gather of its rows
    (``P·A·d`` contiguous floats per observation).
    """

    def __init__(self, networks: list[TabularSFNetwork]):
        first = networks[0]
        tables = [net.table for net in networks]
        stored = np.unique(np.concatenate([table.stored_rows() for table in tables]))
        stack_row = np.full(first.table.n_rows, len(stored), dtype=np.int32)
        stack_row[stored] = np.arange(len(stored), dtype=np.int32)
        stack = np.empty((len(stored) + 1, len(networks), first.table.width), dtype=np.float32)
        for i, table in enumerate(tables):  # by the stored rows: a copy in Π needs no slot map of its own
            stack[:, i] = table.default
            stack[np.searchsorted(stored, table.stored_rows()), i] = table.stored_values()
        self.rows, self.n_actions, self.reward_dim = first.rows, first.n_actions, first.reward_dim
        self._set(stack_row, stack)

    def _set(self, stack_row: np.ndarray, stack: np.ndarray) -> None:
        """Hold ``stack`` ``(states + 1, P, A·d)``, its last state every table's default row, and ``stack_row``."""
        self.n_policies, self.stack_row_numpy = stack.shape[1], stack_row
        self.tables_numpy = stack.reshape(len(stack), -1)
        self._before_last: StackedTables | None = None  # what :meth:`with_table` extended

    def _like(self, stack_row: np.ndarray, stack: np.ndarray) -> StackedTables:
        """A stack of tables of this one's spaces."""
        stacked = copy.copy(self)
        stacked._set(stack_row, stack)
        return stacked

    def _stack3d(self) -> np.ndarray:
        return self.tables_numpy.reshape(len(self.tables_numpy), self.n_policies, -1)

    def with_table(self, network: TabularSFNetwork) -> StackedTables:
        """
        The stack with ``network``'s table as one more policy (what stacking them all again holds, the states it
        stored first seen appended): a copy of this stack instead of every table sorted and scattered again.
        """
        table, old = network.table, self._stack3d()
        rows = table.stored_rows()
        default_state = len(old) - 1
        new_rows = rows[self.stack_row_numpy[rows] == default_state]
        n_states = default_state + len(new_rows)
        stack = np.empty((n_states + 1, self.n_policies + 1, old.shape[2]), dtype=np.float32)
        stack[:default_state, :-1] = old[:-1]
        stack[default_state:, :-1] = old[-1]  # the states new to the stack, and every other: the defaults
        stack_row = self.stack_row_numpy.copy()
        stack_row[stack_row == default_state] = n_states
        stack_row[new_rows] = np.arange(default_state, n_states, dtype=np.int32)
        stack[:, -1] = table.default
        stack[stack_row[rows], -1] = table.stored_values()
        extended = self._like(stack_row, stack)
        extended._before_last, self._before_last = self, None  # one level kept: a new policy tried, then taken out
        return extended

    def without_last(self) -> StackedTables:
        """The stack without its last policy: the one :meth:`with_table` extended, else its other columns."""
        if self._before_last is not None:
            return self._before_last
        return self.columns(list(range(self.n_policies - 1)))

    def columns(self, members: list[int]) -> StackedTables:
        """The stack of the policies ``members`` (in that order): the same states, their columns copied."""
        return self._like(self.stack_row_numpy, self._stack3d().take(members, axis=1))

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        index = self.rows(obs_tensor.cpu().numpy(), check=False)
        rows = self.tables_numpy.take(self.stack_row_numpy.take(index), axis=0)
        return th.from_numpy(rows).view(-1, self.n_policies, self.n_actions, self.reward_dim).transpose(0, 1)

    def q_values_numpy(self, obs: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """GPI action values of a batch, in numpy (CPU sets): cheaper than torch for a few small operations."""
        return self.policy_q_numpy(obs, weights).max(axis=1)

    def attaining(
        self, index: np.ndarray, weights: np.ndarray, left_out: np.ndarray | None, masks: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        GPI's actions of a batch and the members that attain their values, in one compiled call
        (:func:`~sb3_sfgpi.tabular.kernels.gpi_attaining`: numpy's bits; CPU sets).

        :param index: the observations' table rows (:meth:`~sb3_sfgpi.tabular.network.TabularSFNetwork.rows`)
        :param weights: shape ``(d,)``, or ``(batch, d)``: each observation's own; float32
        :param left_out: each observation's member GPI acts without (``-1``: none), or None
        :param masks: the actions each observation has, shape ``(batch, n_actions)``, or None: every action
        :return: the actions ``(batch,)`` and whether each member attains GPI's value of them ``(P, batch)``
        """
        from sb3_sfgpi.tabular.kernels import gpi_attaining  # numba: loaded where tables act

        batch = len(index)
        rows = np.ascontiguousarray(np.broadcast_to(weights, (batch, self.reward_dim)), dtype=np.float32)
        actions, attaining = np.empty(batch, dtype=np.int64), np.empty((self.n_policies, batch), dtype=bool)
        gpi_attaining(
            self.tables_numpy, self.stack_row_numpy.take(index).astype(np.int64), rows,
            np.full(batch, -1, dtype=np.int64) if left_out is None else left_out.astype(np.int64, copy=False),
            np.empty((0, self.n_actions), dtype=bool) if masks is None else masks, actions, attaining,
        )  # fmt: skip
        return actions, attaining

    def policy_q_numpy(self, obs: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """
        Every policy's action values ``w · ψ^π(s, a)`` of a batch, shape ``(batch, P, A)`` (CPU sets).

        :param weights: shape ``(d,)``, or ``(batch, d)``: each observation's own
        """
        index = self.rows(obs)  # raises ValueError for an observation outside the space
        rows = self.tables_numpy.take(self.stack_row_numpy.take(index), axis=0).reshape(len(index), -1, self.reward_dim)
        each = weights if weights.ndim == 1 else weights[:, None, :]
        return weighted_sum(rows, each).reshape(-1, self.n_policies, self.n_actions)


def _stacked_linears(linears: list[Any]) -> tuple[th.Tensor, th.Tensor]:
    """The weights ``(P, in, out)`` and biases ``(P, 1, out)`` of ``P`` Linear layers."""
    weight = th.stack([lin.weight for lin in linears]).transpose(1, 2)
    return weight, th.stack([lin.bias for lin in linears]).unsqueeze(1)


def _stateless_extractor(net: Any) -> bool:
    """Whether a network's features extractor holds no parameters or buffers (its features serve every network)."""
    extractor = net.features_extractor
    return not any(True for _ in extractor.parameters()) and not any(True for _ in extractor.buffers())


def _plain_layers(modules: Any, weighted: tuple[type[nn.Module], ...]) -> bool:
    """
    Whether every module is one of the ``weighted`` layer types with its weight and bias (not a subclass, which may
    compute otherwise; e.g. a layer normalisation without affine has neither) or an activation the files know.
    """
    activations = tuple(_ACTIVATIONS.values())
    for module in modules:
        if type(module) in weighted:
            if module.weight is None or module.bias is None:
                return False
        elif type(module) not in activations:
            return False
    return True


class StackedMLP:
    """
    MLP SF networks stacked layer by layer: weights ``(P, in, out)``, biases ``(P, 1, out)`` for ``P`` networks.

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
                    weight, bias = _stacked_linears([net.sf_net[i] for net in networks])
                    self.layers.append((weight.contiguous(), bias))
                else:
                    self.layers.append(module)

    @staticmethod
    def supports(net: nn.Module) -> bool:
        """An MLP SF network whose features extractor holds no state and whose layers are Linear or activations."""
        if type(net) is not SFNetwork or not isinstance(net.sf_net, nn.Sequential):  # a subclass may add layers
            return False
        return _stateless_extractor(net) and _plain_layers(net.sf_net, (nn.Linear,))

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        features = self.first.extract_features(obs_tensor, self.first.features_extractor)
        x = features.unsqueeze(0).expand(self.n_policies, *features.shape)
        for layer in self.layers:
            if isinstance(layer, tuple):
                x = th.baddbmm(layer[1], x, layer[0])
            else:
                x = layer(x)
        return x.view(self.n_policies, -1, self.n_actions, self.reward_dim)


#: One layer of ``P`` stacked networks: ``(P, batch, in)`` (or ``(batch, in)``, shared) -> ``(P, batch, out)``.
Layer = Callable[[th.Tensor], th.Tensor]


def _stacked_layer(modules: list[Any]) -> Layer:
    """The same layer of ``P`` networks as one :data:`Layer` (as ``vmap`` computes it); an activation as it is."""
    first = modules[0]
    if isinstance(first, nn.Linear):
        weight, bias = _stacked_linears(modules)
        return lambda x: x @ weight + bias
    if isinstance(first, nn.LayerNorm):
        scale = th.stack([module.weight for module in modules]).unsqueeze(1)
        shift = th.stack([module.bias for module in modules]).unsqueeze(1)
        shape, eps = first.normalized_shape, first.eps
        return lambda x: F.layer_norm(x, shape, eps=eps) * scale + shift
    return first


def _stacked_part(heads: list[Any], part: str) -> list[Layer]:
    """The ``nn.Sequential`` named ``part`` of ``P`` heads, stacked layer by layer."""
    sequentials = [getattr(head, part) for head in heads]
    return [_stacked_layer([sequential[i] for sequential in sequentials]) for i in range(len(sequentials[0]))]


def _through(layers: list[Layer], x: th.Tensor) -> th.Tensor:
    """``x`` through ``layers`` in turn."""
    for layer in layers:
        x = layer(x)
    return x


class StackedConditioned:
    """
    Weight-conditioned SF networks (:class:`~sb3_sfgpi.sfdqn.conditioned.ConditionedSFNetwork`), each bound to its
    member's weights, stacked head by head: each ``Linear`` of the ``P`` networks is one batched product and one
    addition of the biases, each layer normalisation one normalisation of the stack followed by each network's scale
    and shift: ``vmap``'s arithmetic, the same bits as :class:`StackedVmap` (``baddbmm``'s fused addition is not).
    """

    def __init__(self, networks: list[ConditionedSFNetwork]):
        first = networks[0]
        self.first = first
        self.n_policies, self.n_actions, self.reward_dim = len(networks), first.n_actions, first.reward_dim
        weights: list[Any] = [net.member_weights for net in networks]
        self.member_weights = th.stack(weights).unsqueeze(1)  # (P, 1, d)
        #: per head: its state features, its weight features (each a layer and an activation), then its layers
        self.heads: list[tuple[list[Layer], list[Layer], list[Layer]]] = []
        with th.no_grad():
            for h in range(len(first.sf_net)):
                each = [net.sf_net[h] for net in networks]
                parts = (_stacked_part(each, part) for part in ("state_features", "weight_features", "layers"))
                self.heads.append(tuple(parts))  # type: ignore[arg-type]

    @staticmethod
    def supports(net: nn.Module) -> bool:
        """A conditioned SF network whose features extractor holds no state and whose layers are the class's own."""
        from sb3_sfgpi.sfdqn.conditioned import ConditionedHead, ConditionedSFNetwork

        if type(net) is not ConditionedSFNetwork or not _stateless_extractor(net):
            return False
        return all(
            type(head) is ConditionedHead
            and _plain_layers([*head.state_features, *head.weight_features, *head.layers], (nn.Linear, nn.LayerNorm))
            for head in net.sf_net
        )

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        features = self.first.extract_features(obs_tensor, self.first.features_extractor)
        weights = self.member_weights.expand(self.n_policies, len(features), self.reward_dim)
        outputs = []
        for state_features, weight_features, layers in self.heads:
            x = _through(state_features, features) * _through(weight_features, weights)
            outputs.append(_through(layers, x))
        psi = outputs[0] if len(outputs) == 1 else th.stack(outputs, dim=1).mean(dim=1)
        return psi.view(self.n_policies, -1, self.n_actions, self.reward_dim)


class StackedVmap:
    """Any networks of one architecture: ``stack_module_state`` + ``vmap`` over ``functional_call``."""

    def __init__(self, networks: list[nn.Module]):
        self.params, self.buffers = stack_module_state(networks)  # type: ignore[arg-type]
        self.skeleton = copy.deepcopy(networks[0]).to("meta")

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        skeleton = self.skeleton

        def one(p: dict[str, th.Tensor], b: dict[str, th.Tensor], x: th.Tensor) -> th.Tensor:
            return functional_call(skeleton, (p, b), (x,))

        return th.vmap(one, in_dims=(0, 0, None))(self.params, self.buffers, obs_tensor)


class LeaveOneOut:
    """
    A stacked set without one of its policies: the others' ``ψ`` (or action values) from the whole set's stack, in
    their order, nothing copied. Each policy's values are those of the whole set's pass.
    """

    def __init__(self, stacked: Stacked, member: int):
        self.stacked, self.member = stacked, member
        self.tabular: bool = numpy_tables(stacked)

    def psi(self, obs_tensor: th.Tensor) -> th.Tensor:
        psi = self.stacked.psi(obs_tensor)
        return th.cat([psi[: self.member], psi[self.member + 1 :]])

    def policy_q_numpy(self, obs: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """The others' action values, shape ``(batch, P - 1, A)`` (CPU tables)."""
        return np.delete(self.stacked.policy_q_numpy(obs, weights), self.member, axis=1)  # type: ignore[union-attr]

    def q_values_numpy(self, obs: np.ndarray, weights: np.ndarray) -> np.ndarray:
        return self.policy_q_numpy(obs, weights).max(axis=1)


#: A set's networks evaluated in one batched pass.
Stacked = StackedTables | StackedMLP | StackedConditioned | StackedVmap | LeaveOneOut


def numpy_tables(stacked: Stacked) -> TypeGuard[StackedTables | LeaveOneOut]:
    """Whether the stack holds tables, whose action values numpy computes (on the CPU)."""
    return isinstance(stacked, StackedTables) or (isinstance(stacked, LeaveOneOut) and stacked.tabular)


def stack_networks(networks: list[nn.Module]) -> StackedTables | StackedMLP | StackedConditioned | StackedVmap:
    """The fastest batched evaluator that fits the networks (all of one architecture)."""
    first = networks[0]
    if isinstance(first, TabularSFNetwork):
        return StackedTables(networks)  # type: ignore[arg-type]
    if StackedMLP.supports(first):
        return StackedMLP(networks)  # type: ignore[arg-type]
    if StackedConditioned.supports(first):
        return StackedConditioned(networks)  # type: ignore[arg-type]
    return StackedVmap(networks)
