"""Domain presets: found through the entry-point group ``sb3_sfgpi.domains``, validated when loaded.

A domain's entry point is a callable returning a plain :class:`dict` (so that environment packages need not import
``sb3_sfgpi``); :meth:`DomainPreset.from_dict` turns it into a typed preset, and a missing or misspelt key is a
one-line error naming the key and the domain.
"""

from __future__ import annotations

import inspect
import json
from collections.abc import Callable, Sequence
from dataclasses import MISSING, Field, dataclass, field, fields
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.run_settings import EPISODE_WEIGHTS, OLS_BATCHES, SHARINGS, VALUE_MODES, RunSettings
from sb3_sfgpi.trust import refuse_unlisted

ENTRY_POINT_GROUP = "sb3_sfgpi.domains"
#: What each entry of ``--w`` weighs in the shipped domains (``--help``).
WEIGHT_HELP = (
    "one per objective, in the domain's order (four-room: blue squares, green triangles, red circles collected; "
    "traffic: vehicles, pedestrians, by their waiting times, or the env's objectives=[...])"
)
#: The settings of a run's ``run.json`` that the commands read to rebuild its env and learners.
CLI_SETTINGS = ("domain", "env_kwargs", "learner_kwargs")


#: The largest count a setting takes (weights, episodes, copies): beyond, a run would not fit in memory or time.
MAX_COUNT = 1_000_000


def _count(minimum: int) -> Callable[[Any], bool]:
    return lambda value: isinstance(value, int) and not isinstance(value, bool) and minimum <= value <= MAX_COUNT


def _one_of(choices: Sequence[str]) -> Callable[[Any], bool]:
    return lambda value: value in choices


#: The settings a preset chooses and ``train --set`` changes: key -> (check, what the value must be).
SETTABLE: dict[str, tuple[Callable[[Any], bool], str]] = {
    "ols_batch": (_one_of(OLS_BATCHES), f"one of {', '.join(OLS_BATCHES)}"),
    "value_mode": (_one_of(VALUE_MODES), f"one of {', '.join(VALUE_MODES)}"),
    "gpi_set": (_one_of(("all", "ccs")), "all or ccs"),
    "sharing": (_one_of(SHARINGS), f"one of {', '.join(SHARINGS)}"),
    "validation_weights": (_count(0), f"an integer in [0, {MAX_COUNT}]"),
    "prune": (lambda value: isinstance(value, bool), "true or false"),
    "admit_together": (lambda value: isinstance(value, bool), "true or false"),
    "pool_replay": (lambda value: isinstance(value, bool), "true or false"),
    "rebind_support": (lambda value: isinstance(value, bool), "true or false"),
    "episode_weights": (_one_of(EPISODE_WEIGHTS), f"one of {', '.join(EPISODE_WEIGHTS)}"),
    "n_test_weights": (_count(1), f"an integer in [1, {MAX_COUNT}]"),
    "value_episodes": (_count(1), f"an integer in [1, {MAX_COUNT}]"),
    "eval_episodes": (_count(1), f"an integer in [1, {MAX_COUNT}]"),
    "eval_workers": (_count(0), f"an integer in [0, {MAX_COUNT}]"),
    "n_envs": (_count(1), f"an integer in [1, {MAX_COUNT}]"),
}
#: The run settings (:class:`~sb3_sfgpi.run_settings.RunSettings`) a domain's data may set: all but those each run
#: chooses (its seed, its weights' algorithm and test weights) and the policy, which is ``learner_kwargs``' entry.
PRESET_SETTINGS = tuple(
    name for name in RunSettings.names() if name not in ("policy", "weights", "test_weights", "seed")
)


@dataclass(frozen=True)
class DomainPreset:
    """
    What ``sb3-sfgpi`` needs to know of a domain. Its data (the entry point's dict) holds the fields below and the
    run settings of :data:`PRESET_SETTINGS` (``learner_kwargs`` with the learners' ``policy``; the others default
    to :class:`~sb3_sfgpi.run_settings.RunSettings`'), which :meth:`from_dict` gathers in ``settings``.

    :param name: the domain's name
    :param make_env: a picklable callable building the PettingZoo ParallelEnv from ``env_kwargs``
    :param env_kwargs: the env's keyword arguments
    :param settings: the run settings of the domain's runs (seed, weights and test weights: the run's own)
    :param iterations: default maximum number of iterations
    :param n_test_weights: default number of Dirichlet(1) test weights of the GPI evaluation
    :param eval_workers: default number of evaluation processes
    :param objectives: the objectives' names, one per reward component
    :param baselines: for ``compare``: name -> env keyword arguments of a controller that needs no actions
    :param episode_metrics: for ``compare`` and its plots: ``[info key, label]`` pairs read from the ``"episode"``
        entry of the last info
    :param step_metrics: ``[info key, label]`` pairs of the per-step infos, summed over agents
    :param compare_weights: the weights ``compare`` evaluates GPI at by default
    :param fixed_weights: the weights of the a priori scalarised reference runs
    :param run_file_env_kwargs: the env arguments a run directory's ``run.json`` may set (an allow-list: none that
        makes the env write files or run programs; default: the keys of ``env_kwargs``; see :mod:`sb3_sfgpi.trust`)
    """

    name: str
    make_env: Callable[..., Any]
    env_kwargs: dict[str, Any]
    settings: RunSettings
    iterations: int
    n_test_weights: int
    eval_workers: int = 0
    objectives: list[str] | None = None
    baselines: dict[str, dict[str, Any]] = field(default_factory=dict)
    episode_metrics: list[list[str]] = field(default_factory=list)
    step_metrics: list[list[str]] = field(default_factory=list)
    compare_weights: list[list[float]] = field(default_factory=list)
    fixed_weights: list[list[float]] = field(default_factory=list)
    run_file_env_kwargs: list[str] | None = None

    @classmethod
    def from_dict(cls, name: str, data: Any) -> DomainPreset:
        """
        The preset of domain ``name`` from its entry point's data.

        :raises UsageError: not a dict, an unknown or missing key, a value of the wrong kind
        """
        if not isinstance(data, dict):
            raise UsageError(f"domain {name!r}: the preset must be a dict, got {type(data).__name__}")
        domain_fields = {f.name: f for f in fields(cls) if f.name not in ("name", "settings")}
        for key in data:
            if key not in domain_fields and key not in PRESET_SETTINGS:
                known = [*domain_fields, *PRESET_SETTINGS]
                raise UsageError(f"domain {name!r}: unknown preset key {key!r} (known: {', '.join(known)})")
        required = [key for key, spec in domain_fields.items() if _required(spec)] + ["learner_kwargs"]
        missing = [key for key in required if key not in data]
        if missing:
            raise UsageError(f"domain {name!r}: the preset lacks {missing[0]!r}")
        learner_kwargs = data["learner_kwargs"]
        if not isinstance(learner_kwargs, dict) or "policy" not in learner_kwargs:
            raise UsageError(f"domain {name!r}: learner_kwargs must be a dict with the learners' 'policy'")
        settings = {key: value for key, value in data.items() if key in PRESET_SETTINGS}
        settings["learner_kwargs"] = {key: value for key, value in learner_kwargs.items() if key != "policy"}
        domain = {key: value for key, value in data.items() if key in domain_fields}
        preset = cls(name=name, settings=RunSettings(policy=learner_kwargs["policy"], **settings), **domain)
        preset._check()
        return preset

    def setting(self, key: str) -> Any:
        """The value of a :data:`SETTABLE` key: one of the run settings, or the preset's own default."""
        return getattr(self.settings, key) if key in RunSettings.names() else getattr(self, key)

    def build_env(self, env_kwargs: dict[str, Any]) -> Any:
        """
        The domain's env with ``env_kwargs``.

        :raises UsageError: the env refuses them (an unknown argument, a value out of range, a file that is not there)
        """
        try:
            return self.make_env(**env_kwargs)
        except (TypeError, ValueError, FileNotFoundError) as error:
            raise UsageError(f"the {self.name} env refuses {env_kwargs}: {error}") from error

    def run_file_env(self, env_kwargs: dict[str, Any], source: Any, given_here: dict[str, Any] | None = None) -> dict:
        """
        The env arguments of a run file, every one on the domain's allow-list (``run_file_env_kwargs``) or
        ``given_here`` for (given on this command line with the same value).

        :param source: the run directory, named in the error
        :raises UsageError: an argument the domain does not take from a run file
        """
        allowed = self.env_kwargs.keys() if self.run_file_env_kwargs is None else self.run_file_env_kwargs
        given_here = given_here or {}
        from_run_file = {
            key: value for key, value in env_kwargs.items() if key not in given_here or given_here[key] != value
        }
        try:
            refuse_unlisted(from_run_file, allowed, f"{source}/run.json: env argument", f"the {self.name} env")
        except ValueError as error:
            raise UsageError(str(error)) from None
        return env_kwargs

    def same_env(self, env_kwargs: dict[str, Any], other: dict[str, Any]) -> bool:
        """
        Whether two runs' env arguments build the same env: equal once each is completed with the defaults of
        ``make_env``'s arguments it leaves out (an argument given at its default is the same as one left out) and
        written as JSON (tuples as lists, paths as strings).
        """
        return self._env_settings(env_kwargs) == self._env_settings(other)

    def _env_settings(self, env_kwargs: dict[str, Any]) -> Any:
        try:
            parameters = inspect.signature(self.make_env).parameters.values()
        except (TypeError, ValueError):  # a callable without a signature: its arguments as given
            parameters = []
        defaults = {p.name: p.default for p in parameters if p.default is not p.empty and p.kind is not p.VAR_KEYWORD}
        return json.loads(json.dumps({**defaults, **env_kwargs}, default=str, sort_keys=True))

    def objective_names(self, env_kwargs: dict[str, Any]) -> list[str] | None:
        """
        The objectives' names of a run: the env's ``objectives`` argument where the run chooses them from a menu (as
        the traffic env's), else the preset's.
        """
        chosen = env_kwargs.get("objectives")
        if isinstance(chosen, list) and chosen and all(isinstance(name, str) for name in chosen):
            return chosen
        return self.objectives

    def _check(self) -> None:
        if not callable(self.make_env):
            raise UsageError(f"domain {self.name!r}: make_env must be callable")
        for key in ("env_kwargs", "baselines"):
            if not isinstance(getattr(self, key), dict):
                raise UsageError(f"domain {self.name!r}: {key} must be a dict")
        for key, value in (("steps_per_iteration", self.settings.steps_per_iteration), ("iterations", self.iterations)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UsageError(f"domain {self.name!r}: {key} must be a positive integer, got {value!r}")
        for key, (check, what) in SETTABLE.items():
            if not check(self.setting(key)):
                raise UsageError(f"domain {self.name!r}: {key} must be {what}, got {self.setting(key)!r}")


def _required(spec: Field) -> bool:
    return spec.default is MISSING and spec.default_factory is MISSING


def available_domains() -> dict[str, EntryPoint]:
    """Domain name -> entry point, from the ``sb3_sfgpi.domains`` entry-point group."""
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def load_domain(name: str) -> DomainPreset:
    """
    The preset of a domain: an installed one, or a registered single-agent Gymnasium id with vector rewards (see
    :mod:`sb3_sfgpi.cli.gym_domains`).

    :raises UsageError: unknown domain, or a preset with a missing or misspelt key
    """
    domains = available_domains()
    if name in domains:
        return DomainPreset.from_dict(name, domains[name].load()())
    from sb3_sfgpi.cli.gym_domains import gym_preset  # Gymnasium (and MO-Gymnasium) only where asked for

    data = gym_preset(name)
    if data is None:
        raise UsageError(
            f"unknown domain {name!r}: neither an installed domain ({', '.join(sorted(domains)) or 'none'}) nor a "
            "registered Gymnasium id"
        )
    return DomainPreset.from_dict(name, data)
