"""sb3-sfgpi: successor features, OLS and GPI for Stable-Baselines3.

The public names are imported when first used (PEP 562): ``import sb3_sfgpi`` and the command line's parser import
neither torch nor Stable-Baselines3; ``from sb3_sfgpi import SFDQN`` imports what SFDQN needs. Importing the package
asks torch's MKL for one code path on every x86 CPU (:mod:`sb3_sfgpi.common.cpu_arithmetic`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from sb3_sfgpi.common.cpu_arithmetic import pin_mkl_code_path

pin_mkl_code_path()  # before anything of the package multiplies matrices: MKL reads it once, at its first call

if TYPE_CHECKING:  # type checkers and Sphinx see the names as imported
    from sb3_sfgpi.admission import Admission
    from sb3_sfgpi.callbacks import OLSCallback, ValueEstimation
    from sb3_sfgpi.common.mo_callbacks import MOEvalCallback
    from sb3_sfgpi.common.mo_evaluation import mo_evaluate_policy
    from sb3_sfgpi.common.parallel_wrappers import (
        FlattenObservations,
        PadActions,
        SelfFirstAgentIds,
        SwapTerminationsTruncations,
    )
    from sb3_sfgpi.common.vec_env import make_mo_vec_env
    from sb3_sfgpi.evaluation import EvaluationConfig
    from sb3_sfgpi.gpi import GPIPolicy
    from sb3_sfgpi.gpi_predictor import GPIPredictor
    from sb3_sfgpi.masfols import MASFOLS
    from sb3_sfgpi.multiagent import MultiAgentRunner
    from sb3_sfgpi.ols import OLS
    from sb3_sfgpi.run_directory import RunDirectory
    from sb3_sfgpi.run_settings import RunSettings
    from sb3_sfgpi.schedules import FixedSchedule, OLSSchedule, RandomSchedule
    from sb3_sfgpi.sfdqn import SFDQN

__version__ = "0.1.0"
__all__ = [
    "MASFOLS",
    "OLS",
    "SFDQN",
    "Admission",
    "EvaluationConfig",
    "FixedSchedule",
    "FlattenObservations",
    "GPIPolicy",
    "GPIPredictor",
    "MOEvalCallback",
    "MultiAgentRunner",
    "OLSCallback",
    "OLSSchedule",
    "PadActions",
    "RandomSchedule",
    "RunDirectory",
    "RunSettings",
    "SelfFirstAgentIds",
    "SwapTerminationsTruncations",
    "ValueEstimation",
    "__version__",
    "make_mo_vec_env",
    "mo_evaluate_policy",
]

#: Public name -> the module that defines it.
_MODULES = {
    "Admission": "sb3_sfgpi.admission",
    "OLSCallback": "sb3_sfgpi.callbacks",
    "ValueEstimation": "sb3_sfgpi.callbacks",
    "MOEvalCallback": "sb3_sfgpi.common.mo_callbacks",
    "mo_evaluate_policy": "sb3_sfgpi.common.mo_evaluation",
    "FlattenObservations": "sb3_sfgpi.common.parallel_wrappers",
    "PadActions": "sb3_sfgpi.common.parallel_wrappers",
    "SelfFirstAgentIds": "sb3_sfgpi.common.parallel_wrappers",
    "SwapTerminationsTruncations": "sb3_sfgpi.common.parallel_wrappers",
    "make_mo_vec_env": "sb3_sfgpi.common.vec_env",
    "EvaluationConfig": "sb3_sfgpi.evaluation",
    "GPIPolicy": "sb3_sfgpi.gpi",
    "GPIPredictor": "sb3_sfgpi.gpi_predictor",
    "MASFOLS": "sb3_sfgpi.masfols",
    "MultiAgentRunner": "sb3_sfgpi.multiagent",
    "OLS": "sb3_sfgpi.ols",
    "RunDirectory": "sb3_sfgpi.run_directory",
    "RunSettings": "sb3_sfgpi.run_settings",
    "FixedSchedule": "sb3_sfgpi.schedules",
    "OLSSchedule": "sb3_sfgpi.schedules",
    "RandomSchedule": "sb3_sfgpi.schedules",
    "SFDQN": "sb3_sfgpi.sfdqn",
}


def __getattr__(name: str) -> Any:
    """A public name, imported from its module on first use (and then kept in this module's namespace)."""
    module = _MODULES.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
