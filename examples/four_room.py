"""Reproduce the paper's Fig. 4: MA-SFOLS + GPI vs Random + GPI on the two-agent Four-Room.

Trains both algorithms for several seeds (``sb3-sfgpi train four-room`` runs as one sweep on Ray: a local Ray with
``--num-cpus`` CPUs, or the cluster at ``--address``), draws the
mean ± std of GPI's return over the 12 test weights after every iteration (``sb3-sfgpi plot``), and prints
per iteration the mean over seeds, the iteration at which each algorithm reaches 95% of its final value and
the wall time of the runs. With ``--apriori-seeds`` it also trains the reference: one learner pair per test weight
and seed, trained a priori for that weight with a whole run's budget (``train --algo fixed``), drawn as a line.
Finished runs are skipped and interrupted ones resumed.

    python examples/four_room.py --seeds 0 1 2 --out runs/fig4
    python examples/four_room.py --seeds 0 1 2 --apriori-seeds 0 --out runs/fig4   # 12 more runs of 6-12 minutes
    python examples/four_room.py --env observation_mode=xy --out runs/fig4-xy --figure docs/figures/four_room_xy.png
    python examples/four_room.py --sharing shared --apriori-seeds 0 --out runs/fig4-shared \
        --figure docs/figures/four_room_shared.png   # one learner both agents act with and feed, a priori too
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from sb3_sfgpi.cli.plot import a_priori_reference, final_test_returns, own_weight_return
from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.cli.sweep_runner import RunSpec, run_sweep
from sb3_sfgpi.common.weights import format_weights, random_weights, same_weight
from sb3_sfgpi.multiagent import SHARINGS
from sb3_sfgpi.plots import align_runs, ols_ended
from sb3_sfgpi.run_directory import RunDirectory

ALGORITHMS = ("ma-sfols", "random")
"""The two curves of Fig. 4."""


def train(args: argparse.Namespace, specs: list[RunSpec]) -> list[Path]:
    """Train (or continue) the runs as one sweep; their directories, in order."""
    outcomes = run_sweep(specs, args.out, address=args.address, num_cpus=args.num_cpus)
    failed = [f"{o.spec.run_name}: {o.error}" for o in outcomes if o.status == "failed"]
    if failed:
        sys.exit("runs failed: " + "; ".join(failed))
    return [outcome.run_dir for outcome in outcomes]


def first_within(curve: np.ndarray, fraction: float = 0.95) -> int:
    """1-based iteration at which ``curve`` first reaches ``fraction`` of its final value."""
    final = curve[-1]
    return int(np.argmax(curve >= fraction * final)) + 1


def observation_mode(env_overrides: list[str]) -> str:
    """The observation mode the runs use (the preset's ``own`` unless ``--env observation_mode=...``)."""
    modes = [item.partition("=")[2] for item in env_overrides if item.startswith("observation_mode=")]
    return modes[-1] if modes else "own"


#: What the figure's title says of the learners: nothing for one per agent (the paper's).
SHARING_TITLES = {"shared": ", one learner shared by both agents"}


def shared_title(sharing: str | None) -> str:
    """What the figure's title says of the learners."""
    return SHARING_TITLES.get(sharing or "", "")


def main() -> None:
    args = parse_args()
    extra = run_options(args)
    jobs = [(algo, seed) for seed in args.seeds for algo in ALGORITHMS]
    specs = [RunSpec("four-room", algo, seed, options=tuple(extra), name=f"{algo}-s{seed}") for algo, seed in jobs]
    trained = train(args, [*specs, *apriori_specs(args, extra)])
    runs, apriori = trained[: len(specs)], trained[len(specs) :]
    plot(args, runs, apriori)
    by_algo = {algo: [run for run, (a, _) in zip(runs, jobs, strict=True) if a == algo] for algo in ALGORITHMS}
    print_curves(by_algo, apriori)
    if apriori:
        for algo, algo_runs in by_algo.items():
            print_per_weight(algo_runs, apriori, algo)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", type=Path, default=Path("runs/fig4"))
    parser.add_argument("--figure", type=Path, default=Path("docs/figures/four_room.png"))
    parser.add_argument("--iterations", type=int, help="iterations per run (default: the domain's)")
    parser.add_argument("--steps-per-iteration", type=int, help="joint steps per iteration (default: the domain's)")
    parser.add_argument("--num-cpus", type=int, help="CPUs of the local Ray: runs at a time (default: all cores)")
    parser.add_argument("--address", help="a Ray cluster to run on (default: RAY_ADDRESS, else a local Ray)")
    parser.add_argument("--apriori-seeds", type=int, nargs="*", default=[], help="seeds of the a-priori reference")
    parser.add_argument("--sharing", choices=list(SHARINGS), help="learners of every run (default: the domain's)")
    parser.add_argument(
        "--env", metavar="KEY=VALUE", action="append", default=[], help="env override, e.g. observation_mode=xy"
    )
    return parser.parse_args()


def run_options(args: argparse.Namespace) -> list[str]:
    """The ``sb3-sfgpi train`` options every run of the figure shares."""
    extra = [f"--env={item}" for item in args.env]
    if args.iterations:
        extra += ["--iterations", str(args.iterations)]
    if args.steps_per_iteration:
        extra += ["--steps-per-iteration", str(args.steps_per_iteration)]
    if args.sharing:
        extra += ["--set", f"sharing={args.sharing}"]
    return extra


def plot(args: argparse.Namespace, runs: list[Path], apriori: list[Path]) -> None:
    """Draw the figure with ``sb3-sfgpi plot``, the a-priori learners as reference lines."""
    title = (
        f"Four-Room, {observation_mode(args.env)} observations{shared_title(args.sharing)}: GPI return over 12 "
        "test weights, both agents"
    )
    fixed = ["--fixed", *map(str, apriori)] if apriori else []
    plot_cli = [sys.executable, "-m", "sb3_sfgpi.cli", "plot", *map(str, runs), "-o", str(args.figure)]
    subprocess.run([*plot_cli, *fixed, "--title", title], check=True)


def print_curves(by_algo: dict[str, list[Path]], apriori: list[Path]) -> None:
    """The table of GPI's mean ± std per iteration of each algorithm, and its end against the a-priori learners."""
    n_iterations = max(max_iterations(runs) for runs in by_algo.values())
    columns = " | ".join(f"it {i}" for i in range(1, 1 + n_iterations))
    print(f"\n| algorithm | {columns} | 95% at | wall time (s) |")
    reference = a_priori_reference(apriori) if apriori else None
    for algo, algo_runs in by_algo.items():
        rows = [read_rows(run) for run in algo_runs]
        ended = [ols_ended(RunDirectory(run)) for run in algo_runs]
        curves = align_runs([{int(r["iteration"]): float(r["mean_return"]) for r in rs} for rs in rows], ended)
        # Runs whose OLS ended early keep their final set to the common length; others stop where they stopped.
        pad = n_iterations - curves.shape[1]
        curves = np.array([extend(row, pad, done) for row, done in zip(curves, ended, strict=True)])
        mean, std = np.nanmean(curves, axis=0), np.nanstd(curves, axis=0)
        wall = np.mean([float(rs[-1]["wall_time"]) for rs in rows])
        cells = " | ".join(f"{m:.3f} ± {s:.3f}" for m, s in zip(mean, std, strict=True))
        print(f"| {algo} | {cells} | {first_within(mean)} | {wall:.0f} |")
        if reference is not None:
            print(f"  final / a priori: {mean[-1] / reference.mean:.3f}")
    if reference is not None:
        print(f"{reference.label}: {reference.mean:.3f} ± {reference.std:.3f}")


def apriori_specs(args: argparse.Namespace, extra: list[str]) -> list[RunSpec]:
    """The a-priori runs: per seed and test weight, the budget of a whole run at once."""
    preset = load_domain("four-room")
    iterations = args.iterations or preset.iterations
    budget = iterations * (args.steps_per_iteration or preset.settings.steps_per_iteration)
    weights = random_weights(3, preset.n_test_weights, rng=0)  # MASFOLS's test weights
    sharing = ["--set", f"sharing={args.sharing}"] if args.sharing else []
    options = (*(item for item in extra if item.startswith("--env")), *sharing, "--iterations", "1")
    return [
        RunSpec(
            "four-room",
            "fixed",
            seed,
            tuple(w),
            (*options, "--steps-per-iteration", str(budget)),
            f"fixed-w{i}-s{seed}",
        )
        for seed in args.apriori_seeds
        for i, w in enumerate(weights)
    ]


def print_per_weight(runs: list[Path], apriori: list[Path], label: str) -> None:
    """Per test weight with a-priori learners, GPI's final w·return (``runs``) beside theirs (mean ± std over
    seeds); test weights without a-priori learners are left out."""
    trained = [own_weight_return(RunDirectory(run)) for run in apriori]
    weights: list[np.ndarray] = []
    for w, _ in trained:
        if not any(same_weight(w, seen) for seen in weights):
            weights.append(w)
    finals = [final_test_returns(RunDirectory(run)) for run in runs]
    print(f"\n| test weight | {label} + GPI, final | a priori | ratio |\n|---|---|---|---|")
    for w in weights:
        theirs = [value for trained_w, value in trained if same_weight(trained_w, w)]
        ours = [float(w @ vector) for final in finals for test_w, vector in final if same_weight(test_w, w)]
        ratio = np.mean(ours) / np.mean(theirs)
        print(f"| {format_weights(w)} | {mean_std(ours)} | {mean_std(theirs)} | {ratio:.3f} |")


def mean_std(values: list[float]) -> str:
    return f"{np.mean(values):.3f} ± {np.std(values):.3f}"


def extend(row: np.ndarray, pad: int, ols_ended: bool) -> np.ndarray:
    """``row`` with ``pad`` more iterations: its last value where OLS ended (the set is complete), else NaN."""
    return np.pad(row, (0, pad), mode="edge") if ols_ended else np.pad(row, (0, pad), constant_values=np.nan)


def read_rows(run: Path) -> list[dict[str, str]]:
    return RunDirectory(run).read_summary()


def max_iterations(runs: list[Path]) -> int:
    return max(len(read_rows(run)) for run in runs)


if __name__ == "__main__":
    main()
