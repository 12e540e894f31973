from sb3_sfgpi.sfdqn.networks import SFNetwork, TabularSFNetwork
from sb3_sfgpi.sfdqn.policies import MlpPolicy, SFDQNPolicy, TabularPolicy
from sb3_sfgpi.sfdqn.sfdqn import SFDQN

__all__ = ["SFDQN", "MlpPolicy", "SFDQNPolicy", "SFNetwork", "TabularPolicy", "TabularSFNetwork"]
