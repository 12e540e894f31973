"""The run directory: where a run keeps its description, Π, evaluations, checkpoint and logs.

Layout (no other module spells these names)::

    run.json           what the run is: its settings (and, from the CLI, the domain and env arguments), with the
                       format's name and version (:data:`RUN_FORMAT`, :data:`RUN_VERSION`)
    policy_set/        Π in the policy-set format of :class:`~sb3_sfgpi.gpi.GPIPolicy` (``manifest.json``), as of
                       the checkpoint; during an iteration also the set it is making (``manifest.next.json``, its
                       files stamped with the iteration), which its checkpoint commits
    evaluation.json    per iteration: the summary row, the weights trained and, per test weight and agent, the
                       vector returns of GPI (discounted and not) and the last infos
    evaluation.csv     per iteration: the summary row
    checkpoint.json    the schedule's state (OLS), next iteration and its weights, number of policies in Π
    software.json      per training process (a new run, each resume): the iteration it started from and what it ran
                       on (:func:`~sb3_sfgpi.common.software.software_versions`); read by no command
    learners/          with learners that go on across iterations (``ConditionedMlpPolicy``): their state after the
                       checkpoint's iteration (``iteration_003.pt``: tensors and plain numbers, see
                       :mod:`sb3_sfgpi.sfdqn.training_state`)
    experience/        with pooled replay (:mod:`sb3_sfgpi.tabular.pooling`): per iteration, the transitions its
                       learners added to the pool (``iteration_001.npz``, ...: counts per (s, a, s'), plain arrays)
    logs/              the runner's SB3 logger (progress.csv, TensorBoard scalars of OLS and GPI)
    tensorboard/       the learners' TensorBoard logs, one folder per agent and iteration
    compare.json       what ``sb3-sfgpi compare`` wrote (by default)
    .lock              the writer's lock (:meth:`RunDirectory.lock`): who writes the run now (pid, host, command)

Every file is written atomically. After an iteration, Π is staged first (evaluation workers load it), then the
evaluation files, and ``checkpoint.json`` last: it is what a resume trusts, so rows beyond its counts (left by an
iteration that was killed) are ignored, and so are experience files beyond its iteration. The checkpoint names its
set by the digest of the staged manifest, and only then does that become ``manifest.json``
(:mod:`sb3_sfgpi.run_policy_set`): a reader loads the checkpoint's set wherever the writer was killed.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi.common.serialization import atomic_write_bytes, atomic_write_json, read_json
from sb3_sfgpi.run_lock import RunDirectoryBusy, RunLock, check_not_written
from sb3_sfgpi.trust import check_learner_kwargs

#: The file of a policy-set directory that describes the set and names its other files (see
#: :mod:`sb3_sfgpi.policy_set_files`).
MANIFEST = "manifest.json"
#: The manifest of the set an iteration stages in ``policy_set/`` until its checkpoint commits it.
STAGED_MANIFEST = "manifest.next.json"

#: The format of ``run.json`` and of the files beside it, and its version: a run of another version is refused.
RUN_FORMAT = "sb3-sfgpi/run"
RUN_VERSION = 1

#: The columns of ``evaluation.csv``, in order.
SUMMARY_FIELDS = (
    "iteration",
    "timesteps",
    "n_policies",
    "ccs_size",
    "mean_return",
    "mean_return_undiscounted",
    "expected_utility",
    "hypervolume",
    "wall_time",
    "eval_time",
)


def summary_scalars(row: dict[str, Any]) -> dict[str, Any]:
    """The logged scalars (``ols/<field>``) of an iteration's summary row; fields without a value are left out."""
    return {f"ols/{key}": row[key] for key in SUMMARY_FIELDS if row.get(key) is not None}


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _weights(value: Any, ndim: int) -> bool:
    """A non-empty array of non-negative finite numbers with ``ndim`` dimensions."""
    if not isinstance(value, list) or not value:
        return False
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return array.ndim == ndim and array.size > 0 and bool(np.isfinite(array).all() and (array >= 0).all())


def _numbered_from_one(history: list[Any]) -> list[Any]:
    """Rows of a run written before 2026-11-23, which numbered iterations from 0, renumbered from 1."""
    if not history or not isinstance(history[0], dict) or history[0].get("iteration") != 0:
        return history
    legacy = [isinstance(row, dict) and _integer(row.get("iteration")) for row in history]
    return [{**row, "iteration": row["iteration"] + 1} if ok else row for row, ok in zip(history, legacy, strict=True)]


def _summary_row(row: Any, number: int) -> bool:
    """Whether ``row`` is the summary of iteration ``number``: its counts integers, its measures finite numbers."""
    if not isinstance(row, dict) or row.get("iteration") != number or not _integer(row["iteration"]):
        return False
    counts = ("timesteps", "n_policies", "ccs_size")
    measures = ("mean_return", "mean_return_undiscounted", "expected_utility", "wall_time", "eval_time")
    finite = all(isinstance(row.get(k), (int, float)) and np.isfinite(row[k]) for k in measures)
    return finite and all(_integer(row.get(k)) for k in counts) and isinstance(row.get("test", []), list)


def _string(value: Any) -> bool:
    return isinstance(value, str)


def _hexadecimal(value: str) -> bool:
    return all(c in "0123456789abcdef" for c in value)


#: What the known settings of ``run.json`` must be (others are kept as they are).
_SETTING_KINDS: dict[str, Callable[[Any], bool]] = {
    **dict.fromkeys(("domain", "algorithm", "policy", "gpi_set", "value_mode", "sharing", "episode_weights"), _string),
    **dict.fromkeys(("env_kwargs", "learner_kwargs"), lambda v: isinstance(v, dict)),
    **dict.fromkeys(("seed", "iterations", "steps_per_iteration", "n_test_weights", "validation_weights"), _integer),
    **dict.fromkeys(("value_episodes", "eval_episodes", "eval_workers", "n_envs"), _integer),
    **dict.fromkeys(("prune", "admit_together", "pool_replay", "rebind_support"), lambda v: isinstance(v, bool)),
    "test_weights": lambda v: _weights(v, 2),
    "weights": lambda v: isinstance(v, str) or _weights(v, 1),
}


#: Files that may be in a run directory before its ``run.json`` (the lock, a sweep's record and log).
_BEFORE_RUN = {".lock", "sweep.json", "train.log"}

__all__ = ["RunDirectory", "RunDirectoryBusy", "RunLock", "summary_scalars"]


class RunDirectory:
    """
    The files of one run (see the module docstring for the layout).

    :param path: the directory (created when something is first written)
    """

    RUN = "run.json"
    CHECKPOINT = "checkpoint.json"
    SOFTWARE = "software.json"
    EVALUATION_JSON = "evaluation.json"
    EVALUATION_CSV = "evaluation.csv"

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._temporary = False

    @classmethod
    def temporary(cls) -> RunDirectory:
        """A run directory in a new temporary folder, deleted by :meth:`remove_temporary`."""
        run_dir = cls(tempfile.mkdtemp(prefix="sfgpi_run_"))
        run_dir._temporary = True
        return run_dir

    def remove_temporary(self) -> None:
        """Delete the folder if :meth:`temporary` made it (a no-op otherwise)."""
        if self._temporary:
            shutil.rmtree(self.path, ignore_errors=True)

    def __repr__(self) -> str:
        return f"RunDirectory({str(self.path)!r})"

    def __str__(self) -> str:
        return str(self.path)

    # --- paths ------------------------------------------------------------------------------------------------
    @property
    def policy_set_dir(self) -> Path:
        return self.path / "policy_set"

    @property
    def logs_dir(self) -> Path:
        return self.path / "logs"

    @property
    def tensorboard_dir(self) -> Path:
        return self.path / "tensorboard"

    @property
    def experience_dir(self) -> Path:
        return self.path / "experience"

    @property
    def compare_file(self) -> Path:
        return self.path / "compare.json"

    def is_run(self) -> bool:
        """Whether the directory describes a run (has ``run.json``)."""
        return (self.path / self.RUN).is_file()

    def lock(self, command: str) -> RunLock:
        """
        Take the directory's writer lock (creating the directory) for as long as the returned lock is held.

        :param command: what the holder does, named to a second writer
        :raises RunDirectoryBusy: another process holds it (the message names its pid, host and command)
        """
        return RunLock(self.path, command)

    def check_new_run(self, settings: dict[str, Any]) -> None:
        """
        Refuse to start a run here unless the directory is missing, empty, or a run of the same ``settings``
        (every key of ``settings`` equal in ``run.json``) that has no checkpoint yet; touches nothing.

        :raises RunDirectoryBusy: another process writes it
        :raises ValueError: a folder that is not a run of these settings
        """
        if not self.path.exists():
            return
        if not self.path.is_dir():
            raise ValueError(f"{self.path} is not a directory")
        check_not_written(self.path)
        others = sorted(p.name for p in self.path.iterdir() if p.name not in _BEFORE_RUN)
        if not others:
            return
        same = False
        if self.is_run():
            try:
                saved = read_json(self.path / self.RUN, "run description")
            except ValueError:
                saved = None
            same = isinstance(saved, dict) and all(
                saved.get(key) == json.loads(json.dumps(value, default=str)) for key, value in settings.items()
            )
        if not same:
            raise ValueError(
                f"{self.path} is not empty and not a run of these settings (it holds {', '.join(others[:3])}"
                f"{', ...' if len(others) > 3 else ''}): nothing was touched; choose another --out"
            )

    def has_checkpoint(self) -> bool:
        """Whether at least one iteration finished (``checkpoint.json`` exists)."""
        return (self.path / self.CHECKPOINT).is_file()

    def has_evaluations(self) -> bool:
        return (self.path / self.EVALUATION_CSV).is_file()

    # --- run.json ---------------------------------------------------------------------------------------------
    def read_config(self, required: Sequence[str] = ()) -> dict[str, Any]:
        """
        The run's description, the kinds of its known settings checked.

        :param required: settings it must hold (e.g. the CLI's ``domain``)
        :raises ValueError: not a run directory, a ``run.json`` that is not a JSON object, a setting of the wrong
            kind, or a required one missing
        """
        if not self.is_run():
            raise ValueError(f"{self.path} is not a run directory (no {self.RUN})")
        path = self.path / self.RUN
        config = read_json(path, "run description")
        if not isinstance(config, dict):
            raise ValueError(f"run description {path} is not a JSON object")
        version = config.pop("version", None)
        if config.pop("format", None) != RUN_FORMAT or type(version) is not int or version != RUN_VERSION:
            raise ValueError(
                f"run description {path} is of format version {version!r}; this version of sb3-sfgpi reads "
                f"version {RUN_VERSION}"
            )
        for key in required:
            if key not in config:
                raise ValueError(f"run description {path} lacks {key!r}")
        for key, value in config.items():
            if key in _SETTING_KINDS and not _SETTING_KINDS[key](value):
                raise ValueError(f"run description {path}: {key!r} has a value of the wrong kind: {value!r}")
        check_learner_kwargs(config.get("learner_kwargs", {}), f"run description {path}")  # an allow-list
        return config

    def write_config(self, config: dict[str, Any]) -> None:
        """Write ``run.json``: ``config`` with the format's name and version."""
        atomic_write_json(self.path / self.RUN, {"format": RUN_FORMAT, "version": RUN_VERSION, **config})

    def write_iteration(self, history: Sequence[dict[str, Any]], checkpoint: dict[str, Any]) -> None:
        """The evaluation files of every iteration so far, then ``checkpoint.json`` (last: a resume trusts it)."""
        atomic_write_json(self.path / self.EVALUATION_JSON, list(history))
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(history)
        atomic_write_bytes(self.path / self.EVALUATION_CSV, out.getvalue().encode())
        atomic_write_json(self.path / self.CHECKPOINT, checkpoint)

    def record_software(self, versions: dict[str, str]) -> None:
        """
        Add a training process's machine and package versions to ``software.json``, with the iteration it starts
        from (that of the checkpoint, 0 without one).

        :raises ValueError: a ``software.json`` that is not a list of records
        """
        path = self.path / self.SOFTWARE
        records = read_json(path, "software record") if path.exists() else []
        if not isinstance(records, list):
            raise ValueError(f"software record {path} is not a JSON list: move it away to go on")
        iteration = self.read_checkpoint()["iteration"] if self.has_checkpoint() else 0
        atomic_write_json(path, [*records, {"from_iteration": iteration, **versions}])

    def read_checkpoint(self) -> dict[str, Any]:
        """
        The last checkpoint, its structure checked.

        :raises ValueError: missing, unreadable or malformed (naming the field)
        """
        path = self.path / self.CHECKPOINT
        state = read_json(path, "checkpoint")
        if not isinstance(state, dict):
            raise ValueError(f"checkpoint {path} is not a JSON object")
        for key in ("iteration", "timesteps", "n_policies"):
            value = state.get(key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"checkpoint {path}: {key!r} must be a non-negative integer, got {value!r}")
        if not isinstance(state.get("schedule"), dict) or not isinstance(state["schedule"].get("ols"), dict):
            raise ValueError(f"checkpoint {path}: no 'schedule' state (written by another version of sb3-sfgpi?)")
        named = state.get("policy_set")
        if named is not None and not (isinstance(named, str) and len(named) == 64 and _hexadecimal(named)):
            raise ValueError(f"checkpoint {path}: 'policy_set' must be null or a SHA-256 digest, got {named!r}")
        if not isinstance(state.get("learners", False), bool):
            raise ValueError(f"checkpoint {path}: 'learners' must be true or false, got {state['learners']!r}")
        next_weights = state.get("next_weights")
        if next_weights is not None and not (
            isinstance(next_weights, dict) and all(_weights(w, 1) for w in next_weights.values())
        ):
            raise ValueError(
                f"checkpoint {path}: 'next_weights' must be null or agent -> weights, got {next_weights!r}"
            )
        return state

    def write_experience(self, iteration: int, arrays: dict[str, np.ndarray]) -> None:
        """What iteration ``iteration`` (numbered from 1) added to the pooled replay, as plain arrays in an ``.npz``."""
        out = io.BytesIO()
        np.savez(out, allow_pickle=False, **arrays)
        atomic_write_bytes(self._experience_file(iteration), out.getvalue())

    def read_experience(self, iteration: int) -> dict[str, np.ndarray]:
        """
        The arrays :meth:`write_experience` wrote for ``iteration``, read without unpickling anything.

        :raises ValueError: a missing or unreadable file
        """
        path = self._experience_file(iteration)
        if not path.is_file():
            raise ValueError(
                f"{path} does not exist: the run pooled its replay, and iteration {iteration}'s is missing"
            )
        try:
            with np.load(path, allow_pickle=False) as data:
                return {key: data[key] for key in data.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
            raise ValueError(f"{path} is not an experience file (truncated or corrupt?): {error}") from error

    def write_learners(self, iteration: int, states: dict[str, Any]) -> None:
        """The states of the learners that go on across iterations, after ``iteration`` (numbered from 1)."""
        import torch as th

        out = io.BytesIO()
        th.save({"iteration": iteration, "learners": states}, out)
        atomic_write_bytes(self._learners_file(iteration), out.getvalue())

    def read_learners(self, iteration: int) -> dict[str, Any]:
        """
        Learner name -> the state :meth:`write_learners` wrote after ``iteration``, read with ``weights_only=True``.

        :raises ValueError: a missing, unreadable or foreign file
        """
        import torch as th

        path = self._learners_file(iteration)
        try:
            data = th.load(path, map_location="cpu", weights_only=True)
        except Exception as error:  # torch raises many types for truncated files and refused pickles
            message = f"{path}: the learners' state after iteration {iteration} is missing or unreadable: {error}"
            raise ValueError(message) from None
        if (
            not isinstance(data, dict)
            or data.get("iteration") != iteration
            or not isinstance(data.get("learners"), dict)
        ):
            raise ValueError(f"{path} is not the learners' state after iteration {iteration}")
        return data["learners"]

    def remove_learners_before(self, iteration: int) -> None:
        """Delete the learners' states of iterations before ``iteration`` (once a checkpoint no longer names them)."""
        for path in sorted(self.learners_dir.glob("iteration_*.pt")):
            if path.name < self._learners_file(iteration).name:
                path.unlink(missing_ok=True)

    @property
    def learners_dir(self) -> Path:
        return self.path / "learners"

    def _learners_file(self, iteration: int) -> Path:
        return self.learners_dir / f"iteration_{iteration:03d}.pt"

    def _experience_file(self, iteration: int) -> Path:
        return self.experience_dir / f"iteration_{iteration:03d}.npz"

    def read_history(self, n_iterations: int | None = None) -> list[dict[str, Any]]:
        """The rows of ``evaluation.json``, or its first ``n_iterations`` (those the checkpoint counts)."""
        path = self.path / self.EVALUATION_JSON
        history = read_json(path, "evaluation")
        if not isinstance(history, list) or (n_iterations is not None and len(history) < n_iterations):
            raise ValueError(f"evaluation {path} does not hold the checkpoint's rows")
        history = _numbered_from_one(history if n_iterations is None else history[:n_iterations])
        for number, row in enumerate(history, start=1):
            if not _summary_row(row, number):
                raise ValueError(f"evaluation {path}: row {number} is not the summary of iteration {number}")
        return history

    def read_summary(self) -> list[dict[str, str]]:
        """
        The rows of ``evaluation.csv`` (one per finished iteration, values as strings).

        :raises ValueError: no evaluation yet
        """
        if not self.has_evaluations():
            raise ValueError(f"{self.path} has no {self.EVALUATION_CSV} yet")
        with open(self.path / self.EVALUATION_CSV, newline="") as handle:
            rows = list(csv.DictReader(handle))
        if rows and rows[0].get("iteration") == "0":  # numbered from 0 before 2026-11-23
            return [{**row, "iteration": str(int(row["iteration"]) + 1)} for row in rows]
        return rows
