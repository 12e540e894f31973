"""The weights conditioned learners act and train for, episode by episode: their own, or one drawn from their support.

A learner conditioned on the weights (``ConditionedMlpPolicy``) learns ψ(s, a, w) for its iteration's weight and for
the weights OLS already holds (its support), but its transitions come from acting for its own weight only: the other
weights learn off-policy from a behaviour that was never theirs. With ``"support"`` (GPI-LS's behaviour) each episode
acts, and trains the minibatch half of the learner's own weight, for a weight drawn uniformly from the support (the
iteration's weight among them); what joins Π is still the network bound to the iteration's weight.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.run_settings import EPISODE_WEIGHTS
from sb3_sfgpi.sfdqn import SFDQN


class EpisodeWeights:
    """
    Draws the weights of conditioned learners at every episode start of an iteration (``"support"``), or nothing
    (``"own"``). The draws of an iteration come from ``derive_seed(seed, iteration, learner name, "episode-weights")``,
    so a resumed run, which repeats an interrupted iteration, draws the same weights. With several copies of the env
    (``n_envs``) a weight is drawn whenever one of them starts an episode: a learner acts for one weight in all of them.

    :param kind: ``"own"`` or ``"support"`` (see the module)
    :raises ValueError: another kind
    """

    def __init__(self, kind: str = EPISODE_WEIGHTS[0]):
        if kind not in EPISODE_WEIGHTS:
            raise ValueError(f"episode_weights must be one of {EPISODE_WEIGHTS}, got {kind!r}")
        self.kind = kind
        self._learners: Mapping[str, SFDQN] = {}
        self._own: dict[str, np.ndarray] = {}
        self._generators: dict[str, np.random.Generator] = {}

    def start(self, learners: Mapping[str, SFDQN], seed: int, iteration: int) -> None:
        """
        An iteration starts: remember the conditioned learners' own weights, seed their draws.

        :param learners: the iteration's learners conditioned on the weights, by name
            (:attr:`~sb3_sfgpi.multiagent.MultiAgentRunner.conditioned_learners`)
        """
        if self.kind == "own":
            return
        self._learners = dict(learners)
        self._own = {name: learner.weights for name, learner in self._learners.items()}
        seeds = {name: derive_seed(seed, iteration, name, "episode-weights") for name in self._learners}
        self._generators = {name: np.random.default_rng(seeds[name]) for name in self._learners}

    def draw(self) -> None:
        """Episodes start (the env was reset): every conditioned learner takes a weight drawn from its support."""
        for name, learner in self._learners.items():
            support = learner.weight_support
            if support is not None:
                learner.set_weights(support[self._generators[name].integers(len(support))])

    def end(self) -> None:
        """The iteration's steps are done: the learners take their own weights back (members are bound to them)."""
        for name, learner in self._learners.items():
            learner.set_weights(self._own[name])
        self._learners, self._own, self._generators = {}, {}, {}
