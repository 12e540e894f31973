"""sb3-sfgpi: successor features, OLS and GPI for Stable-Baselines3."""

from sb3_sfgpi.admission import Admission
from sb3_sfgpi.callbacks import OLSCallback, ValueEstimation
from sb3_sfgpi.common.mo_callbacks import MOEvalCallback
from sb3_sfgpi.common.mo_evaluation import mo_evaluate_policy
from sb3_sfgpi.common.parallel_wrappers import FlattenObservations, SwapTerminationsTruncations
from sb3_sfgpi.common.vec_env import make_mo_vec_env
from sb3_sfgpi.evaluation import EvaluationConfig
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.gpi_predictor import GPIPredictor
from sb3_sfgpi.masfols import MASFOLS
from sb3_sfgpi.multiagent import MultiAgentRunner
from sb3_sfgpi.ols import OLS
from sb3_sfgpi.run_directory import RunDirectory
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
    "RandomSchedule",
    "RunDirectory",
    "SwapTerminationsTruncations",
    "ValueEstimation",
    "__version__",
    "make_mo_vec_env",
    "mo_evaluate_policy",
]
