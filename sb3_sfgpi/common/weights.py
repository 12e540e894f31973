"""Preference weights on the probability simplex.

A weight vector ``w`` of length ``d`` scalarizes a vector reward ``r`` into ``w · r``.
Every public entry point of the library passes user weights through :func:`validate_weights`.

**The same numbers on every machine.** Every ``w · v`` that a decision depends on (greedy and GPI actions, TD
targets, planning, OLS, validation scores) is :func:`weighted_sum`: element-wise products added in a fixed order.
A matrix product (``v @ w``) hands the sum to BLAS (numpy: OpenBLAS; torch: MKL/oneDNN), which picks its kernel at
run time from the CPU (and ``OPENBLAS_CORETYPE``): kernels differ in the order of the additions and in fusing them
into FMAs, and a kernel may even give two identical rows different results, depending on where they sit in the
matrix. An exact tie between actions (identical ``ψ`` rows, or rows that differ only where ``w`` is 0) then went to
whichever action the kernel rounded up, and a seeded run gave different numbers on different machines.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch as th

Array = TypeVar("Array", np.ndarray, "th.Tensor")


def _is_tensor(value: Any) -> bool:
    """Whether ``value`` is a torch tensor, without importing torch: there is none unless torch was imported."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(value, torch.Tensor)


def validate_weights(weights, reward_dim: int, name: str = "weights") -> np.ndarray:
    """
    Check a preference weight vector and return it normalised onto the simplex.

    Positive weights that do not sum to one are rescaled (``[2, 1]`` becomes ``[2/3, 1/3]``):
    the argmax of ``w · ψ`` does not change, and values stay comparable across weights.

    :param weights: array-like of length ``reward_dim``
    :param reward_dim: number of objectives ``d``
    :param name: how the argument is called in error messages
    :return: float64 array of shape ``(reward_dim,)`` with ``w >= 0`` and ``sum(w) == 1``
    :raises ValueError: wrong length, NaN or infinite, negative, or all-zero weights
    """
    if _is_tensor(weights):  # one that requires grad too
        weights = weights.detach().cpu().numpy()
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be a sequence of {reward_dim} numbers, got {weights!r}") from error
    if w.ndim != 1 or w.shape[0] != reward_dim:
        raise ValueError(f"{name} must have length {reward_dim} (one per objective), got shape {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError(f"{name} must be finite, got {w.tolist()} (NaN or inf)")
    if np.any(w < 0):
        raise ValueError(f"{name} must be non-negative, got {w.tolist()}")
    if w.max() <= 0:
        raise ValueError(f"{name} must not be all zero, got {w.tolist()}")
    if not np.isfinite(w.sum()):  # huge weights: into [0, 1] first, as their sum overflows
        w = w / w.max()
    return w / w.sum()


def validate_weight_rows(weights: np.ndarray, reward_dim: int) -> np.ndarray:
    """
    :func:`validate_weights` of every row of a ``(batch, reward_dim)`` array at once: the same checks, the same
    normalised values bit for bit (each row's sum is numpy's sum of that row), the first bad row's error.

    :return: float64 array of the same shape
    :raises ValueError: as :func:`validate_weights`, for the first bad row
    """
    w = np.asarray(weights, dtype=np.float64)
    rows_fit = w.ndim == 2 and w.shape[1] == reward_dim and len(w) > 0
    if not (rows_fit and np.isfinite(w).all() and (w >= 0).all() and (w.max(axis=1) > 0).all()):
        return np.array([validate_weights(row, reward_dim) for row in w]).reshape(w.shape)  # the first bad row raises
    sums = w.sum(axis=1)
    overflowing = ~np.isfinite(sums)
    if overflowing.any():  # huge weights: into [0, 1] first, as their sum overflows
        w = w.copy()
        w[overflowing] /= w[overflowing].max(axis=1, keepdims=True)
        sums = w.sum(axis=1)
    return w / sums[:, None]


def weighted_sum(values: Array, weights: np.ndarray | th.Tensor) -> Array:
    """
    ``w · v`` over the last axis, the same bits on every machine: ``(v_0 w_0 + v_1 w_1) + v_2 w_2 + ...``.

    Each product and each sum is one correctly rounded IEEE operation (numpy's and torch's element-wise kernels,
    whatever their SIMD width), added in the order of the objectives; no BLAS, no FMA, no reduction whose order
    depends on the CPU or the number of threads. The consequences:

    * identical rows give identical results, wherever they are in ``values`` (exact ties stay exact ties);
    * rows that differ only where ``w`` is 0 give identical results (``v_k · 0`` adds an exact 0);
    * the result depends only on the inputs, so every decision made from it (an argmax, a comparison) is the same
      on every machine.

    :param values: numpy array or torch tensor of shape ``(..., d)``
    :param weights: shape ``(d,)``, or broadcastable against ``values`` (e.g. ``(batch, 1, d)``); converted to the
        dtype (and device) of ``values``
    :return: shape ``values.shape[:-1]``, in the dtype of ``values``
    """
    if _is_tensor(values):
        torch = sys.modules["torch"]  # imported: values is a tensor
        w = torch.as_tensor(weights, dtype=values.dtype, device=values.device)
        return _sum_of_columns(values * w)
    w = np.asarray(weights, dtype=values.dtype)
    if values.size <= _SMALL:  # one product of the whole array (fewest calls; same operations, same order)
        return _sum_of_columns(values * w)
    total = values[..., 0] * w[..., 0]  # column by column: no temporary of the size of values
    for k in range(1, values.shape[-1]):
        total += values[..., k] * w[..., k]
    return total


#: Arrays up to this many elements are multiplied at once by :func:`weighted_sum` (the same bits either way).
_SMALL = 2048


def _sum_of_columns(products: Array) -> Array:
    """``(p_0 + p_1) + p_2 + ...`` over the last axis."""
    if products.shape[-1] == 1:
        return products[..., 0].clone() if _is_tensor(products) else products[..., 0].copy()
    total = products[..., 0] + products[..., 1]
    for k in range(2, products.shape[-1]):
        total += products[..., k]
    return total


def simplex_extrema(reward_dim: int) -> list[np.ndarray]:
    """
    The corners of the weight simplex: one unit vector per objective.

    :param reward_dim: number of objectives ``d``
    :return: ``d`` float64 arrays ``e_0, ..., e_{d-1}``
    """
    return [np.eye(reward_dim)[i] for i in range(reward_dim)]


def random_weights(reward_dim: int, n: int | None = None, rng: np.random.Generator | int | None = None) -> np.ndarray:
    """
    Weights drawn uniformly from the simplex (Dirichlet with all concentrations 1).

    :param reward_dim: number of objectives ``d``
    :param n: how many; ``None`` for a single vector
    :param rng: a numpy ``Generator`` or a seed
    :return: shape ``(reward_dim,)`` when ``n`` is None, else ``(n, reward_dim)``
    """
    generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    return generator.dirichlet(np.ones(reward_dim), size=n)


#: Two weight vectors within this of each other (max-norm) are the same weight (run files round them).
SAME_WEIGHT = 1e-3


def same_weight(a: np.ndarray | Sequence[float], b: np.ndarray | Sequence[float]) -> bool:
    """Whether two weight vectors are the same weight: within :data:`SAME_WEIGHT` of each other, max-norm."""
    return bool(np.abs(np.asarray(a) - np.asarray(b)).max() <= SAME_WEIGHT)


def format_weights(w: Sequence[float]) -> str:
    """``[0.2,0.8]``: weights rounded to 3 decimals, the one way output, labels and legends write them."""
    return "[" + ",".join(f"{x:g}" for x in np.round(w, 3)) + "]"
