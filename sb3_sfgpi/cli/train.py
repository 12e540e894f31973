"""``sb3-sfgpi train DOMAIN``: MA-SFOLS + GPI (or Random + GPI, or fixed-weight learners) with a domain's preset."""

from __future__ import annotations

import argparse
import signal
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np

from sb3_sfgpi.callbacks import VALUE_MODES
from sb3_sfgpi.cli.errors import TrainingStopped, UsageError
from sb3_sfgpi.cli.presets import CLI_SETTINGS, WEIGHT_HELP, DomainPreset, load_domain
from sb3_sfgpi.cli.values import check_weights, key_values
from sb3_sfgpi.masfols import MASFOLS, SETTING_DEFAULTS
from sb3_sfgpi.multiagent import SHARINGS
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.schedules import OLS_BATCHES

ALGORITHMS = {"ma-sfols": "ols", "random": "random"}  # --algo -> MASFOLS weights (fixed: the --w weights)


def add_parser(sub: Any) -> None:
    """The ``train`` sub-command's arguments."""
    train = sub.add_parser("train", help="build a policy set with MA-SFOLS (or random weights)")
    _add_run_arguments(train)
    _add_method_arguments(train.add_argument_group("method (each default: the domain's)"))
    _add_machine_arguments(train.add_argument_group("machine"))


def _add_run_arguments(train: Any) -> None:
    """What to train: the domain, the algorithm, its budget, seed and run directory."""
    train.add_argument("domain", help="four-room, traffic, or another installed domain")
    train.add_argument(
        "--algo",
        choices=["ma-sfols", "random", "fixed"],
        default="ma-sfols",
        help="ma-sfols: OLS corner weights; random: Dirichlet(1) weights; fixed: every agent learns for --w from "
        "scratch (a priori scalarisation), in one iteration of iterations x steps-per-iteration steps",
    )
    train.add_argument("--w", type=float, nargs="+", help=f"the preference weights of --algo fixed, {WEIGHT_HELP}")
    train.add_argument(
        "--budget-from",
        type=Path,
        metavar="RUN",
        help="--algo fixed: train as many steps per agent as the run in RUN did (e.g. an MA-SFOLS run that OLS "
        "ended before its iteration cap)",
    )
    train.add_argument("--iterations", type=int, help="maximum number of iterations (default: the domain's)")
    train.add_argument("--steps-per-iteration", type=int, help="joint env steps per iteration (default: the domain's)")
    train.add_argument(
        "--n-envs",
        type=int,
        help="train on K copies of the env, each in its own process, stepped together (every learner gets K times "
        "the transitions per joint step; SB3's n_envs). Default 1",
    )
    train.add_argument("--seed", type=int, default=0)
    train.add_argument("--out", type=Path, help="run directory (default: runs/<domain>-<algo>-s<seed>)")
    train.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    train.add_argument(
        "--env",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override an env argument of the domain (VALUE is read as JSON, else as a string), e.g. num_seconds=200",
    )
    train.add_argument("--learner", metavar="KEY=VALUE", action="append", default=[], help="override an SFDQN argument")
    train.add_argument("--n-test-weights", type=int, help="test weights of the GPI evaluation (default: the domain's)")


def _add_method_arguments(group: Any) -> None:
    """The levers of MA-SFOLS + GPI: how weights are handed out, values measured, policies admitted."""
    group.add_argument(
        "--ols-batch",
        choices=list(OLS_BATCHES),
        help="--algo ma-sfols: how an iteration takes its agents' weights from the OLS queue: top, the highest "
        "priorities (the paper's Algorithm 1); spread, each next one as if the weights handed out before it in the "
        "iteration brought no improvement (the agents do not train for nearly the same weight); same, the highest "
        "one for every agent (they learn beside partners acting for their weight); same-after-extrema, top while "
        "simplex extrema are queued, same after. Default: the domain's",
    )
    group.add_argument(
        "--value-mode",
        choices=list(VALUE_MODES),
        help="how a new policy's value for OLS is measured: joint, the new learners acting together; shared, each "
        "new policy run by every agent; gpi, the agents acting by GPI over the set and the new policies at the "
        "learner's weights (SFOLS, GPI-LS). Default: the domain's",
    )
    group.add_argument(
        "--transfer", action="store_true", default=None, help="start new learners from the best policy in the set"
    )
    group.add_argument(
        "--gpi-behaviour",
        action="store_true",
        default=None,
        help="new learners act epsilon-greedily by GPI over the set and themselves (SFOLS's behaviour), not alone",
    )
    group.add_argument(
        "--sharing",
        choices=list(SHARINGS),
        help="independent: one learner per agent (the paper); experience: one learner per agent that also stores the "
        "transitions of the agents training for the same weights; shared: one learner per iteration that every agent "
        "acts with and feeds (parameter sharing: one weight per iteration). Default: the domain's",
    )
    group.add_argument(
        "--validation-weights",
        type=int,
        metavar="N",
        help="a new policy joins the set only if GPI does at least as well with it on the simplex extrema and N "
        "Dirichlet(1) validation weights (0: every new policy joins; default: the domain's; not for --algo fixed)",
    )
    group.add_argument(
        "--prune",
        action=argparse.BooleanOptionalAction,
        help="after every iteration, also retire from the set the policies without which GPI does better on the "
        "validation weights (needs validation weights; default: the domain's)",
    )
    group.add_argument(
        "--admit-together",
        action=argparse.BooleanOptionalAction,
        help="after an iteration's policies were validated one by one, also try those left out together: they join "
        "the set if GPI does at least as well with them all (needs validation weights; default: the domain's)",
    )
    group.add_argument(
        "--replan",
        action=argparse.BooleanOptionalAction,
        help="old policies keep learning: after every iteration, plan every policy of the set again, for its own "
        "weights, on every transition the run has recorded (tabular learners; default: the domain's)",
    )


def _add_machine_arguments(group: Any) -> None:
    """Where the run executes: threads, device, evaluation workers, progress bars."""
    group.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="torch threads of the training process (default 1: the networks are small, and more threads only "
        "contend with the simulator and the evaluation workers)",
    )
    group.add_argument(
        "--device",
        default="auto",
        help="where the learners run: auto (tables on the CPU, MLPs on CUDA where there is one), cpu, cuda, cuda:N",
    )
    group.add_argument(
        "--eval-workers",
        type=int,
        help="evaluate GPI in this many worker processes, each with its own env (0: in the training process; "
        "default: the domain's)",
    )
    group.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    """Train (or continue) a run; print its last iteration."""
    if args.torch_threads < 1:
        raise UsageError(f"--torch-threads must be positive, got {args.torch_threads}")
    preset = load_domain(args.domain)
    config = _run_config(args, preset)
    run_dir = RunDirectory(args.out or Path("runs") / _default_name(args, config))
    if args.resume:
        vouched = config["env_kwargs"]  # the preset's and --env's: not from the run file
        config = _resumed_config(args, run_dir, config)
        preset.run_file_env(config["env_kwargs"], run_dir, vouched)
    elif run_dir.has_checkpoint():
        raise UsageError(f"{run_dir} already holds a run: pass --resume to continue it or choose another --out")
    eval_workers = preset.eval_workers if args.eval_workers is None else args.eval_workers
    if eval_workers < 0:
        raise UsageError(f"--eval-workers must be 0 or more, got {eval_workers}")
    config["eval_workers"] = eval_workers  # does not change the results: may differ on resume

    import torch as th

    th.set_num_threads(args.torch_threads)
    if not args.resume:  # a folder that is not a run of these settings is refused untouched
        run_dir.check_new_run({key: config[key] for key in ("domain", "algorithm", "seed", "weights", "env_kwargs")})
    new_directory = not run_dir.path.exists()
    lock = _created(run_dir).lock(f"sb3-sfgpi train {args.domain} --seed {args.seed} --out {run_dir}")  # one writer
    try:
        model = _model(args, preset, preset.build_env(config["env_kwargs"]), _created(run_dir), config)
    except (ValueError, UsageError):  # refused settings: leave no empty run directory behind
        if new_directory:
            lock.discard()
            with suppress(OSError):
                run_dir.path.rmdir()
        raise
    try:
        with _sigterm_as_interrupt():
            model.learn(config["iterations"], progress_bar=not args.no_progress)
    except (RuntimeError, OSError, KeyboardInterrupt) as error:  # a dead simulator, a full disk, Ctrl-C, SIGTERM
        raise TrainingStopped(_stopped_message(args, run_dir, model, error)) from error
    finally:
        model.close()
        lock.release()
    _print_result(run_dir, model)
    return 0


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (``kill``, a batch scheduler) stops training as Ctrl-C does: the same message, the same resume."""

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt("SIGTERM")

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread: signals stay as they are
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_config(args: argparse.Namespace, preset: DomainPreset) -> dict[str, Any]:
    """What the run is, from the preset and the options: stored in ``run.json`` (the MASFOLS settings join it)."""
    iterations = preset.iterations if args.iterations is None else args.iterations
    steps_per_iteration = preset.steps_per_iteration if args.steps_per_iteration is None else args.steps_per_iteration
    n_test_weights = preset.n_test_weights if args.n_test_weights is None else args.n_test_weights
    for name, value in (
        ("--n-envs", 1 if args.n_envs is None else args.n_envs),
        ("--iterations", iterations),
        ("--steps-per-iteration", steps_per_iteration),
        ("--n-test-weights", n_test_weights),
    ):
        if value < 1:
            raise UsageError(f"{name} must be positive, got {value}")
    if args.algo != "fixed" and (args.w is not None or args.budget_from is not None):
        raise UsageError("--w and --budget-from are only for --algo fixed")
    if args.algo == "fixed" and args.w is None:
        raise UsageError("--algo fixed needs the preference weights --w")
    learner_kwargs = {**preset.learner_kwargs, "device": args.device, **key_values(args.learner, "--learner")}
    config = {
        "domain": args.domain,
        "algorithm": args.algo,
        "seed": args.seed,
        "iterations": iterations,
        "steps_per_iteration": steps_per_iteration,
        "transfer": bool(args.transfer),
        "gpi_behaviour": bool(args.gpi_behaviour),
        "env_kwargs": {**preset.env_kwargs, **key_values(args.env, "--env")},
        "policy": learner_kwargs.pop("policy"),
        "learner_kwargs": learner_kwargs,
        "n_test_weights": n_test_weights,
        "weights": ALGORITHMS.get(args.algo) or check_weights(args.w, "--w"),
        "ols_batch": _ols_batch(args, preset),
        "value_mode": args.value_mode or preset.value_mode,
        "validation_weights": (validation_weights := _validation_weights(args, preset)),
        "prune": _validation_rule("--prune", args.prune, preset.prune, validation_weights),
        "admit_together": _validation_rule(
            "--admit-together", args.admit_together, preset.admit_together, validation_weights
        ),
        "replan": preset.replan if args.replan is None else args.replan,
        "sharing": args.sharing or preset.sharing,
        "n_envs": SETTING_DEFAULTS["n_envs"] if args.n_envs is None else args.n_envs,
    }
    if args.algo == "fixed":
        config.update(_fixed_budget(args, iterations, steps_per_iteration))
    return config


def _ols_batch(args: argparse.Namespace, preset: DomainPreset) -> str:
    """How MA-SFOLS takes a round's weights from the queue: the option's or the domain's; "top" for other algos."""
    if args.ols_batch is None:
        return preset.ols_batch if args.algo == "ma-sfols" else "top"
    if args.algo != "ma-sfols":
        raise UsageError(f"--ols-batch is only for --algo ma-sfols (OLS weights), not --algo {args.algo}")
    return args.ols_batch


def _validation_weights(args: argparse.Namespace, preset: DomainPreset) -> int:
    """The number of validation weights: the option's or the domain's; 0 for fixed weights (nothing to choose)."""
    if args.validation_weights is None:
        return 0 if args.algo == "fixed" else preset.validation_weights
    if args.algo == "fixed":
        raise UsageError("--validation-weights is not for --algo fixed: every policy of a fixed run is kept")
    if args.validation_weights < 0:
        raise UsageError(f"--validation-weights must be 0 or more, got {args.validation_weights}")
    return args.validation_weights


def _validation_rule(option: str, given: bool | None, domains: bool, validation_weights: int) -> bool:
    """Whether the validation rule ``option`` is on: as given, else the domain's where there are validation weights."""
    if given is None:
        return domains and validation_weights > 0
    if given and not validation_weights:
        raise UsageError(f"{option} needs validation weights (--validation-weights N with N > 0)")
    return given


def _fixed_budget(args: argparse.Namespace, iterations: int, steps_per_iteration: int) -> dict[str, Any]:
    """The same number of steps per agent as an MA-SFOLS run of ``iterations`` iterations, in one iteration."""
    budget: dict[str, Any] = {"iterations": iterations, "steps_per_iteration": steps_per_iteration}
    steps = iterations * steps_per_iteration
    if args.budget_from is not None:
        source = RunDirectory(args.budget_from)
        if not source.has_checkpoint():
            raise UsageError(f"--budget-from: {args.budget_from} has no checkpoint")
        steps = source.read_checkpoint()["timesteps"]
        budget = {"from": str(args.budget_from), "timesteps": steps}
    return {"iterations": 1, "steps_per_iteration": steps, "budget": budget}


def _default_name(args: argparse.Namespace, config: dict[str, Any]) -> str:
    weights = config["weights"]
    tag = "" if isinstance(weights, str) else "-w" + "-".join(f"{x:g}" for x in np.round(weights, 4))
    return f"{args.domain}-{args.algo}{tag}-s{args.seed}"


def _resumed_config(args: argparse.Namespace, run_dir: RunDirectory, config: dict[str, Any]) -> dict[str, Any]:
    """The stored configuration with the new iteration cap; refuses options given that would change the run."""
    if not run_dir.is_run():
        raise UsageError(f"--resume: {run_dir} is not a run directory (no {RunDirectory.RUN})")
    saved = run_dir.read_config(required=CLI_SETTINGS)
    for option, key in (("--env", "env_kwargs"), ("--learner", "learner_kwargs")):
        if getattr(args, option[2:]) and config[key] != saved.get(key):
            raise UsageError(f"--resume: {option} would change the run's {key} ({saved.get(key)})")
    for option in (
        "--ols-batch",
        "--value-mode",
        "--steps-per-iteration",
        "--n-test-weights",
        "--transfer",
        "--gpi-behaviour",
        "--validation-weights",
        "--prune",
        "--admit-together",
        "--replan",
        "--sharing",
        "--n-envs",
    ):
        key = option[2:].replace("-", "_")
        stored = saved.get(key, SETTING_DEFAULTS.get(key))
        if getattr(args, key) is not None and config[key] != stored:
            raise UsageError(f"--resume: {option} {config[key]} would change the run's {key} ({stored})")
    for key in ("domain", "algorithm", "seed", "weights"):
        if saved.get(key) != config.get(key):
            raise UsageError(f"--resume: {run_dir} is a run with {key}={saved.get(key)!r}, not {config.get(key)!r}")
    return {**saved, "iterations": config["iterations"]}


def _created(run_dir: RunDirectory) -> RunDirectory:
    """The run directory, created if needed; a one-line error where it cannot be."""
    try:
        run_dir.path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"--out {run_dir.path}: cannot create the run directory ({error.strerror})") from error
    return run_dir


def _model(
    args: argparse.Namespace, preset: DomainPreset, env: Any, run_dir: RunDirectory, config: dict[str, Any]
) -> MASFOLS:
    """A new MASFOLS for the run, or the stored one continued (``--resume``)."""
    unstored = dict(eval_workers=config["eval_workers"], env_fn=preset.make_env, env_kwargs=config["env_kwargs"])
    if args.resume:
        run_dir.write_config(config)
        return MASFOLS.load(run_dir.path, env, verbose=1, **unstored)
    return MASFOLS(
        env,
        policy=config["policy"],
        weights=config["weights"],
        ols_batch=config["ols_batch"],
        steps_per_iteration=config["steps_per_iteration"],
        learner_kwargs=config["learner_kwargs"],
        test_weights=config["n_test_weights"] if isinstance(config["weights"], str) else None,  # fixed: at --w
        seed=config["seed"],
        run_dir=run_dir.path,
        value_mode=config["value_mode"],
        value_episodes=preset.value_episodes,
        eval_episodes=preset.eval_episodes,
        gpi_set=preset.gpi_set,
        transfer=config["transfer"],
        gpi_behaviour=config["gpi_behaviour"],
        validation_weights=config["validation_weights"],
        prune=config["prune"],
        admit_together=config["admit_together"],
        replan=config["replan"],
        sharing=config["sharing"],
        n_envs=config["n_envs"],
        run_info=config,
        verbose=1,
        **unstored,
    )


def _stopped_message(args: argparse.Namespace, run_dir: RunDirectory, model: MASFOLS, error: BaseException) -> str:
    """One line: where training stopped, that the last checkpoint is intact, and the command that continues it."""
    done = run_dir.read_checkpoint()["iteration"] if run_dir.has_checkpoint() else 0
    if isinstance(error, KeyboardInterrupt):
        reason = f"interrupted by {error}" if str(error) else "interrupted"
    else:
        reason = f"{type(error).__name__}: {error}"
    reason = " ".join(reason.split())  # one line
    weights = model.settings["weights"]
    return (
        f"training stopped in iteration {done + 1} ({reason}). The checkpoint of the last finished "
        f"iteration ({done} done) in {run_dir} is intact: continue with "
        f"`sb3-sfgpi train {args.domain} --algo {args.algo} --seed {args.seed} --out {run_dir} --resume"
        + ("" if args.iterations is None else f" --iterations {args.iterations}")
        + ("" if isinstance(weights, str) else " --w " + " ".join(f"{x:g}" for x in weights))
        + "`"
    )


def _print_result(run_dir: RunDirectory, model: MASFOLS) -> None:
    if not model.history:
        print(f"{run_dir}: nothing to do")
        return
    last = model.history[-1]
    print(
        f"{run_dir}: {last['iteration']} iterations, |Π|={last['n_policies']}, CCS={last['ccs_size']}, "
        f"mean w·return (discounted)={last['mean_return']:.4f}, {last['wall_time']:.1f}s"
        + (" (OLS ended: the set is a CCS)" if model.callback.ended_by_schedule else "")
    )
