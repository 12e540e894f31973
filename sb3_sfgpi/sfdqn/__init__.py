from sb3_sfgpi.sfdqn.networks import SFNetwork
from sb3_sfgpi.sfdqn.policies import MlpPolicy, SFDQNPolicy
from sb3_sfgpi.sfdqn.sfdqn import SFDQN
from sb3_sfgpi.sfdqn.tabular_policy import TabularPolicy
from sb3_sfgpi.tabular.network import TabularSFNetwork

__all__ = ["SFDQN", "MlpPolicy", "SFDQNPolicy", "SFNetwork", "TabularPolicy", "TabularSFNetwork"]
