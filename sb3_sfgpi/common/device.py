"""Where learners and policy sets run: one rule for SFDQN and GPIPolicy."""

from __future__ import annotations

import torch as th


def resolve_device(
    device: th.device | str = "auto", tabular: bool = False, cuda_available: bool | None = None
) -> th.device:
    """
    The device a learner or a policy set runs on.

    ``"auto"``: the CPU for tables (their updates and GPI lookups run in numpy on the table's memory); for other
    networks CUDA where it is available, else the CPU (as SB3's ``get_device``). An explicit device is kept,
    except that CUDA falls back to the CPU where it is unavailable (as SB3's ``get_device``); a table refuses any
    device but the CPU, on every machine.

    :param device: ``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:1"``, ... or a ``torch.device``
    :param tabular: whether the networks are tables (``TabularPolicy``, a set of tabular SF networks)
    :param cuda_available: whether CUDA can be used; ``None`` asks torch
    :return: the device
    :raises ValueError: a table on a device other than the CPU
    """
    if cuda_available is None:
        cuda_available = th.cuda.is_available()
    if isinstance(device, str) and device == "auto":
        return th.device("cuda" if cuda_available and not tabular else "cpu")
    resolved = th.device(device)
    if tabular and resolved.type != "cpu":
        raise ValueError(f"tables (TabularPolicy, tabular policy sets) run on the CPU only, got device={str(device)!r}")
    if resolved.type == "cuda" and not cuda_available:
        return th.device("cpu")
    return resolved
