"""``sb3-sfgpi train DOMAIN``: MA-SFOLS + GPI (or Random + GPI, or fixed-weight learners) with a domain's preset."""

from __future__ import annotations

import argparse
import functools
import sys
from contextlib import suppress
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sb3_sfgpi.cli.errors import TrainingStopped, UsageError
from sb3_sfgpi.cli.presets import CLI_SETTINGS, WEIGHT_HELP, DomainPreset, load_domain
from sb3_sfgpi.cli.settings import SETTABLE, check_resumed, method_settings
from sb3_sfgpi.cli.values import check_weights, key_values
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_settings import RunSettings
from sb3_sfgpi.trust import check_learner_kwargs

if TYPE_CHECKING:
    from sb3_sfgpi.masfols import MASFOLS

ALGORITHMS = {"ma-sfols": "ols", "random": "random"}  # --algo -> MASFOLS weights (fixed: the --w weights)


def add_parser(sub: Any) -> None:
    """The ``train`` sub-command's arguments."""
    train = sub.add_parser("train", help="build a policy set with MA-SFOLS (or random weights)")
    train.add_argument(
        "domain", help="four-room, traffic, another installed domain, or an MO-Gymnasium id (deep-sea-treasure-v0)"
    )
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
        help="--algo fixed: train as many steps per agent as the run in RUN did",
    )
    train.add_argument("--iterations", type=int, help="maximum number of iterations (default: the domain's)")
    train.add_argument("--steps-per-iteration", type=int, help="joint env steps per iteration (default: the domain's)")
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
    train.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help=f"override a method setting of the domain's preset: {', '.join(SETTABLE)}",
    )
    train.add_argument(
        "--device",
        default="auto",
        help="where the learners run: auto (tables on the CPU, MLPs on CUDA where there is one), cpu, cuda, cuda:N",
    )
    train.add_argument("--no-progress", action="store_true", help="no progress bars (none either unless on a terminal)")


def run(args: argparse.Namespace) -> int:
    """Train (or continue) a run; print a header, a line per iteration and the result."""
    preset = load_domain(args.domain)
    config, given = _run_config(args, preset)
    run_dir = RunDirectory(_checked_out(args.out or Path("runs") / _default_name(args, config)))
    if args.resume:
        given_here = config["env_kwargs"]  # the preset's and --env's: not from the run file
        config = _resumed_config(args, run_dir, config, given)
        preset.run_file_env(config["env_kwargs"], run_dir, given_here)
    elif run_dir.has_checkpoint():
        raise UsageError(f"{run_dir} already holds a run: pass --resume to continue it or choose another --out")

    import torch as th

    from sb3_sfgpi.cli.interrupts import Interrupts

    th.set_num_threads(1)  # small networks: more threads only contend with the simulator and the evaluation workers
    if not args.resume:  # a folder that is not a run of these settings is refused untouched
        run_dir.check_new_run({key: config[key] for key in ("domain", "algorithm", "seed", "weights", "env_kwargs")})
    new_directory = not run_dir.path.exists()
    lock = _created(run_dir).lock(f"sb3-sfgpi train {args.domain} --seed {args.seed} --out {run_dir}")  # one writer
    try:
        model = _model(args, preset, preset.build_env(config["env_kwargs"]), run_dir, config)
    except (ValueError, UsageError):  # refused settings: leave no empty run directory behind
        if new_directory:
            lock.discard()
            with suppress(OSError):
                run_dir.path.rmdir()
        raise
    print(_header(args, preset, config, run_dir), flush=True)
    interrupts = Interrupts()
    try:
        with interrupts.caught():
            model.learn(config["iterations"], interrupts, progress_bar=not args.no_progress and sys.stderr.isatty())
            if interrupts.received is not None:  # its KeyboardInterrupt was lost: the training stopped at a step
                raise interrupts.received
    except (Exception, KeyboardInterrupt) as error:
        cause = interrupts.received or error  # an interrupt, whatever it became where it landed
        if not isinstance(cause, (RuntimeError, OSError, KeyboardInterrupt)):  # a dead simulator, a full disk
            raise
        raise TrainingStopped(_stopped_message(args, run_dir, model, cause)) from error
    finally:
        model.close()
        lock.release()
    _print_result(run_dir, model)
    return 0


def _header(args: argparse.Namespace, preset: DomainPreset, config: dict[str, Any], run_dir: RunDirectory) -> str:
    """One line: what is trained, with which budget and objectives, and where it goes."""
    weights = config["weights"]
    algorithm = args.algo if isinstance(weights, str) else "fixed w=[" + ", ".join(f"{x:g}" for x in weights) + "]"
    objectives = preset.objective_names(config["env_kwargs"]) or [f"objective {i}" for i in range(len(weights))]
    return (
        f"sb3-sfgpi train {args.domain}: {algorithm}, seed {config['seed']}, up to {config['iterations']} x "
        f"{config['steps_per_iteration']:,} steps, objectives: {', '.join(objectives)} -> {run_dir}"
        + (" (resumed)" if args.resume else "")
    )


def _run_config(args: argparse.Namespace, preset: DomainPreset) -> tuple[dict[str, Any], dict[str, Any]]:
    """
    What the run is, from the preset and the options: stored in ``run.json`` (the MASFOLS settings join it).

    :return: the configuration, and the settings given with ``--set``
    """
    iterations = preset.iterations if args.iterations is None else args.iterations
    steps_per_iteration = args.steps_per_iteration
    if steps_per_iteration is None:
        steps_per_iteration = preset.settings.steps_per_iteration
    for name, value in (("--iterations", iterations), ("--steps-per-iteration", steps_per_iteration)):
        if value < 1:
            raise UsageError(f"{name} must be positive, got {value}")
    if not 0 <= args.seed < 2**32:  # numpy's and torch's seeds are 32-bit unsigned integers
        raise UsageError(f"--seed must be an integer in [0, 2**32), got {args.seed}")
    if args.algo != "fixed" and (args.w is not None or args.budget_from is not None):
        raise UsageError("--w and --budget-from are only for --algo fixed")
    if args.algo == "fixed" and args.w is None:
        raise UsageError("--algo fixed needs the preference weights --w")
    settings, given = method_settings(preset, args.set, args.algo)
    preset_learner = {"policy": preset.settings.policy, **preset.settings.learner_kwargs}
    learner_kwargs = {**preset_learner, "device": args.device, **key_values(args.learner, "--learner")}
    config = {
        "domain": args.domain,
        "algorithm": args.algo,
        "seed": args.seed,
        "iterations": iterations,
        "steps_per_iteration": steps_per_iteration,
        "env_kwargs": {**preset.env_kwargs, **key_values(args.env, "--env")},
        "policy": learner_kwargs.pop("policy"),
        "learner_kwargs": learner_kwargs,
        "weights": ALGORITHMS.get(args.algo) or check_weights(args.w, "--w"),
        **settings,
    }
    check_learner_kwargs(learner_kwargs, "--learner")  # what a resume would refuse, refused before the run starts
    if args.algo == "fixed":
        config.update(_fixed_budget(args, iterations, steps_per_iteration))
    return config, given


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
    return f"{args.domain.replace('/', '_')}-{args.algo}{tag}-s{args.seed}"


def _resumed_config(
    args: argparse.Namespace, run_dir: RunDirectory, config: dict[str, Any], given: dict[str, Any]
) -> dict[str, Any]:
    """The stored configuration with the new iteration cap; refuses options given that would change the run."""
    if not run_dir.is_run():
        raise UsageError(f"--resume: {run_dir} is not a run directory (no {RunDirectory.RUN})")
    saved = run_dir.read_config(required=CLI_SETTINGS)
    for option, key in (("--env", "env_kwargs"), ("--learner", "learner_kwargs")):
        if getattr(args, option[2:]) and config[key] != saved.get(key):
            raise UsageError(f"--resume: {option} would change the run's {key} ({saved.get(key)})")
    if args.steps_per_iteration is not None and config["steps_per_iteration"] != saved.get("steps_per_iteration"):
        raise UsageError(
            f"--resume: --steps-per-iteration {config['steps_per_iteration']} would change the run's "
            f"steps_per_iteration ({saved.get('steps_per_iteration')})"
        )
    check_resumed(given, saved)
    for key in ("domain", "algorithm", "seed", "weights"):
        if saved.get(key) != config.get(key):
            raise UsageError(f"--resume: {run_dir} is a run with {key}={saved.get(key)!r}, not {config.get(key)!r}")
    eval_workers = config["eval_workers"] if "eval_workers" in given else saved.get("eval_workers", 0)
    return {**saved, "iterations": config["iterations"], "eval_workers": eval_workers}


#: The longest file or folder name most file systems take (ext4, APFS, NTFS: 255 bytes).
MAX_NAME_BYTES = 255


def _checked_out(path: Path) -> Path:
    """The run directory's path, refused in one line where a name in it is longer than file systems take."""
    too_long = [part for part in path.parts if len(part.encode()) > MAX_NAME_BYTES]
    if too_long:
        raise UsageError(f"--out: the name {too_long[0][:24]}... is longer than {MAX_NAME_BYTES} bytes")
    return path


def _created(run_dir: RunDirectory) -> RunDirectory:
    """
    The run directory (its names checked by :func:`_checked_out`), created if needed; a one-line error where it
    cannot be.
    """
    try:
        run_dir.path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"--out {run_dir.path}: cannot create the run directory ({error.strerror})") from error
    return run_dir


def _model(
    args: argparse.Namespace, preset: DomainPreset, env: Any, run_dir: RunDirectory, config: dict[str, Any]
) -> MASFOLS:
    """A new MASFOLS for the run, or the stored one continued (``--resume``)."""
    # The learners (torch, SB3, scipy): imported once the options and the run directory are checked.
    from sb3_sfgpi.masfols import MASFOLS

    env_fn = functools.partial(preset.make_env, **config["env_kwargs"])
    workers = config["eval_workers"]
    if args.resume:
        run_dir.write_config(config)
        return MASFOLS.load(run_dir.path, env, verbose=1, env_fn=env_fn, eval_workers=workers)
    test_weights = None if not isinstance(config["weights"], str) else config["n_test_weights"]  # fixed: at --w
    chosen = {name: config[name] for name in RunSettings.names() if name != "test_weights"}
    settings = RunSettings(**chosen, test_weights=test_weights)
    model = MASFOLS.from_settings(env, settings, env_fn, run_dir.path, eval_workers=workers, verbose=1)
    model.run_info = {**config, **model.run_info}
    return model


def _stopped_message(args: argparse.Namespace, run_dir: RunDirectory, model: MASFOLS, error: BaseException) -> str:
    """One line: where training stopped, that the last checkpoint is intact, and the command that continues it."""
    done = run_dir.read_checkpoint()["iteration"] if run_dir.has_checkpoint() else 0
    if isinstance(error, KeyboardInterrupt):
        reason = f"interrupted by {error}" if str(error) else "interrupted"
    else:
        reason = f"{type(error).__name__}: {error}"
    reason = " ".join(reason.split())  # one line
    weights = model.settings.weights
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
        + (_ols_end(last["ccs_size"], model.runner.reward_dim) if model.callback.ended_by_schedule else "")
    )


def _ols_end(ccs_size: int, reward_dim: int) -> str:
    """
    Why OLS ended, for the result line. One learned value that dominates all the others is OLS's end (one policy
    optimal for every weight), but it is also what learners that learned too little give (policies that reach no
    reward but differ in a cost only), so the line says what to check.
    """
    if ccs_size == 1 and reward_dim > 1:
        return (
            " (OLS ended: one learned value dominates all the others, so no weight is left to try; where the "
            "objectives trade off, the learners need more steps: --steps-per-iteration)"
        )
    return " (OLS ended: the set is a CCS)"
