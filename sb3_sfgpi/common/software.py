"""What a run was computed with: the machine and the versions of the packages its numbers depend on.

The same seed gives the same numbers on any CPU with the same packages (on x86, any with AVX2: the code path of
torch's matrix products that :mod:`~sb3_sfgpi.common.cpu_arithmetic` asks for, recorded as ``mkl``); another torch,
numpy or env package may change a deep learner's arithmetic, or an env's dynamics, and with them every number after
the first step. A run directory keeps :func:`software_versions` of every process that trained it (``software.json``),
and the benchmarks print them in their header, so that two runs that differ can be told apart by what they ran on.
"""

from __future__ import annotations

import importlib.metadata
import platform
import sys
from pathlib import Path

from sb3_sfgpi.common.cpu_arithmetic import mkl_code_path

#: The distributions whose versions are recorded, where installed (the learners', the envs', the tabular core's).
DISTRIBUTIONS = (
    "sb3-sfgpi",
    "torch",
    "numpy",
    "scipy",
    "numba",
    "stable-baselines3",
    "gymnasium",
    "pettingzoo",
    "supersuit",
    "mo-gymnasium",
    "momaland",
    "eclipse-sumo",
    "libsumo",
)


def cpu_model() -> str:
    """The CPU's model name (Linux's ``/proc/cpuinfo``), else what :mod:`platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def software_versions() -> dict[str, str]:
    """
    The machine and the versions of :data:`DISTRIBUTIONS` installed here, as plain strings.

    :return: ``python``, ``system`` (OS, release, architecture), ``cpu``, ``mkl`` (the code path of torch's matrix
        products, where torch is imported and has MKL), ``gpu`` where torch sees a CUDA card, then each installed
        distribution's version by its name
    """
    versions = {
        "python": platform.python_version(),
        "system": f"{platform.system()} {platform.release()} {platform.machine()}",
        "cpu": cpu_model(),
    }
    if (mkl := mkl_code_path()) is not None:
        versions["mkl"] = mkl
    torch = sys.modules.get("torch")  # not imported for this: a process without torch trains no network
    if torch is not None and torch.cuda.is_available():
        versions["gpu"] = f"{torch.cuda.get_device_name(0)} (CUDA {torch.version.cuda})"
    for name in DISTRIBUTIONS:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return versions
