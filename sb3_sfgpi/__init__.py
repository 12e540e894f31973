"""sb3-sfgpi: successor features, OLS and GPI for Stable-Baselines3."""

from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.sfdqn import SFDQN

__version__ = "0.1.0"
__all__ = ["SFDQN", "GPIPolicy", "__version__"]
