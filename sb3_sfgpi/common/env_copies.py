"""Copies of a PettingZoo ParallelEnv, each in its own process, stepped together.

One process per copy: a simulator that allows one instance per process (libsumo) runs ``k`` times, and the copies
step in parallel with each other and with the learners in the main process. Each copy is built by a picklable
``env_fn(**env_kwargs)`` in a spawned process and its composite observations are flattened, as the runner's own
env is. SuperSuit's vector wrappers (``pettingzoo_env_to_vec_env_v1`` + ``concat_vec_envs_v1``) do not fit: their
shared reward buffer holds one float per agent (vector rewards do not fit in it), and agents that leave the episode
early need ``black_death``, which feeds zero observations and rewards to the learners as if they were transitions.
"""

from __future__ import annotations

import multiprocessing as mp
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from sb3_sfgpi.common.parallel_wrappers import as_parallel_env

#: The key of an env's ``metadata`` that says its simulator allows one live instance per process (libsumo): its copies
#: run in processes of their own, never beside it.
ONE_PER_PROCESS = "one_per_process"
#: What a copy returns for a step: observations, rewards, terminations, truncations, infos, agents still in it.
StepResult = tuple[dict, dict, dict, dict, dict, list[str]]
#: What a copy returns for a reset: observations, infos, agents in it.
ResetResult = tuple[dict, dict, list[str]]


def build_copy(env_fn: Callable[..., Any], env_kwargs: Mapping[str, Any]) -> Any:
    """
    A copy of an env, as a ParallelEnv, built without the warnings its constructor gives: building the env it copies
    gave them already (MO-Gymnasium's minecart warns of its spaces' bounds each time, twice, and a run builds about 50
    copies an iteration for its evaluations).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return as_parallel_env(env_fn(**env_kwargs))


def _serve(pipe: Any, env_fn: Callable[..., Any], env_kwargs: Mapping[str, Any]) -> None:
    """The loop of a copy's process: build the env, then answer reset/step/close."""
    env = build_copy(env_fn, env_kwargs)
    try:
        while True:
            command, data = pipe.recv()
            if command == "close":
                break
            try:
                if command == "reset":
                    observations, infos = env.reset(seed=data)
                    pipe.send(("ok", (observations, infos, list(env.agents))))
                else:
                    pipe.send(("ok", (*env.step(data), list(env.agents))))
            except Exception as error:  # the simulator failed: the main process raises it
                pipe.send(("error", f"{type(error).__name__}: {error}"))
    finally:
        env.close()


class SingleCopy:
    """
    An env in this process as the one copy of :class:`EnvCopies`' interface (training without copies).

    :param env: the env
    """

    def __init__(self, env: Any):
        self.env = env

    def __len__(self) -> int:
        return 1

    def reset(self, seeds: Sequence[int | None], copies: Sequence[int] | None = None) -> list[ResetResult]:
        observations, infos = self.env.reset(seed=seeds[0])
        return [(observations, infos, list(self.env.agents))]

    def step(self, actions: Sequence[dict[str, Any]]) -> list[StepResult]:
        return [(*self.env.step(actions[0]), list(self.env.agents))]

    def close(self) -> None:
        pass  # the env belongs to the caller


class EnvCopies:
    """
    ``n`` copies of an env, each in its own spawned process.

    :param env_fn: picklable env constructor
    :param env_kwargs: its keyword arguments
    :param n: number of copies
    """

    def __init__(self, env_fn: Callable[..., Any], env_kwargs: Mapping[str, Any], n: int):
        context = mp.get_context("spawn")
        self._pipes, self._processes = [], []
        for _ in range(n):
            parent, child = context.Pipe()
            process = context.Process(target=_serve, args=(child, env_fn, dict(env_kwargs)), daemon=True)
            process.start()
            child.close()
            self._pipes.append(parent)
            self._processes.append(process)

    def __len__(self) -> int:
        return len(self._pipes)

    def reset(self, seeds: Sequence[int | None], copies: Sequence[int] | None = None) -> list[ResetResult]:
        """
        Reset ``copies`` (default: all) with ``seeds`` (one each).

        :return: per copy, its observations, infos and agents
        """
        copies = range(len(self)) if copies is None else copies
        return self._ask([(copy, ("reset", seed)) for copy, seed in zip(copies, seeds, strict=True)])

    def step(self, actions: Sequence[dict[str, Any]]) -> list[StepResult]:
        """Step every copy with its agents' actions, all at once; per copy what its ``step`` returned and its agents."""
        return self._ask([(copy, ("step", copy_actions)) for copy, copy_actions in enumerate(actions)])

    def _ask(self, requests: list[tuple[int, tuple[str, Any]]]) -> list[Any]:
        for copy, request in requests:
            self._pipes[copy].send(request)
        answers = []
        for copy, _ in requests:
            try:
                status, answer = self._pipes[copy].recv()
            except EOFError as error:
                raise RuntimeError(f"env copy {copy} died (its process exited)") from error
            if status == "error":
                raise RuntimeError(f"env copy {copy} failed: {answer}")
            answers.append(answer)
        return answers

    def close(self) -> None:
        """Stop the copies' processes (each closes its env). Safe to call several times."""
        for pipe in self._pipes:
            try:
                pipe.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for process in self._processes:
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
        self._pipes, self._processes = [], []


class SideBySide:
    """
    An env and copies of it built in this process (each once, then kept), for episodes run side by side.

    :param env: the env itself, the last of the envs :meth:`envs` gives
    :param env_fn: the constructor of its copies, or None (then there are none)
    :param env_kwargs: the constructor's keyword arguments
    """

    def __init__(self, env: Any, env_fn: Callable[..., Any] | None, env_kwargs: Mapping[str, Any] | None):
        self.env = env
        self._env_fn = None if env.metadata.get(ONE_PER_PROCESS) else env_fn
        self._env_kwargs = dict(env_kwargs or {})
        #: the copies built so far
        self.copies: list[Any] = []

    def envs(self, n: int) -> list[Any] | None:
        """
        ``n`` envs: ``n − 1`` copies, then the env; None where no copy can be built (no ``env_fn``, or a simulator that
        allows one instance per process: ``metadata[ONE_PER_PROCESS]``, SUMO's through libsumo).
        """
        if self._env_fn is None:
            return None
        while len(self.copies) < n - 1:
            self.copies.append(build_copy(self._env_fn, self._env_kwargs))
        return [*self.copies[: n - 1], self.env] if n else []

    def close(self) -> None:
        """Close the copies (the env itself is its owner's)."""
        for env in self.copies:
            env.close()
        self.copies = []
