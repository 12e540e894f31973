"""Observations handed to ``predict`` by users: plain numeric arrays, or a one-line error."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch as th


def numeric_array(observation: Any) -> np.ndarray:
    """
    ``observation`` as a numeric numpy array: a torch tensor is detached and copied to the CPU (one that requires
    grad included), a nested list becomes an array.

    :raises ValueError: an observation that is not numbers (strings, objects), naming its dtype, or not finite
    """
    if isinstance(observation, th.Tensor):
        observation = observation.detach().cpu().numpy()
    array = np.asarray(observation)
    if array.dtype.kind not in "biuf":
        raise ValueError(f"observations must be numbers (bool, int or float), got an array of dtype {array.dtype}")
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise ValueError("observations must be finite numbers, got NaN or inf")
    return array
