"""GPI's own estimate against its return, iteration by iteration, for a finished MA-SFOLS run.

For every iteration ``k`` of the run, Π is cut to what it was after iteration ``k`` (the policies of iterations
``1..k`` that validation had not retired by then) and, for every test weight of the run and every agent, two numbers
are compared:

* predicted: ``max_π max_a w · ψπ(s0, a)``, the value GPI expects from the agent's first observation;
* returned: ``w · (discounted return)`` of the agents acting by GPI (the run's evaluation episode seeds).

With exact successor features the return is at least the prediction (GPI's theorem). A prediction above the return
is an overestimate: some policy's ψ is wrong where GPI follows it. The script prints the means over test weights and
agents and the largest overestimate.

With ``--union OTHER_RUN`` (a run of the same domain and test weights, e.g. Random + GPI beside MA-SFOLS) it prints
instead, per test weight, GPI's mean w·return over the agents with the final Π of each run and with their union: where
the union reaches the better of the two, the other run's policies were missing from the worse one (coverage); where it
falls below it, the worse run's policies mislead GPI (interference).

Run: ``python examples/gpi_diagnostics.py RUN_DIR [--union OTHER_RUN]`` (e.g. runs of ``sb3-sfgpi train four-room``)
"""

from __future__ import annotations

import argparse

import numpy as np

from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import load_policy_set


def predicted_and_returned(policy_set: GPIPolicy, env, test_weights: np.ndarray, gamma: float, seed: int):
    """Per (test weight, agent): GPI's predicted value at the first observation and its discounted w·return."""
    predicted, returned = [], []
    for i, w in enumerate(test_weights):
        episode_seed = derive_seed(seed, "eval", i)
        observations, _ = env.reset(seed=episode_seed)
        result = run_episodes(env, policy_set.joint_policy(w), 1, gamma, seed=episode_seed)
        for agent in env.possible_agents:
            predicted.append(float(policy_set.q_values(np.asarray(observations[agent])[None], w).max()))
            returned.append(float(w @ result.mean_discounted(agent)))
    return np.array(predicted), np.array(returned)


def union_per_weight(sets: dict[str, GPIPolicy], env, test_weights: np.ndarray, gamma: float, seed: int) -> None:
    """Print GPI's mean w·return over the agents per test weight for each set, and the sets' means."""
    returns = {}
    for name, policy_set in sets.items():
        _, returned = predicted_and_returned(policy_set, env, test_weights, gamma, seed)
        returns[name] = returned.reshape(len(test_weights), -1).mean(axis=1)
    print("test weight | " + " | ".join(f"{name} (|Π|={len(sets[name])})" for name in sets))
    for i, w in enumerate(test_weights):
        print(f"{np.round(w, 3).tolist()} | " + " | ".join(f"{returns[name][i]:.3f}" for name in sets))
    print("mean | " + " | ".join(f"{returns[name].mean():.4f}" for name in sets))


def final_set(run_dir: RunDirectory) -> GPIPolicy:
    """Π as the run's last checkpoint has it (retired policies left out)."""
    state = run_dir.read_checkpoint()
    return load_policy_set(run_dir, state["n_policies"], iteration=state["iteration"])


def joined(first: GPIPolicy, second: GPIPolicy) -> GPIPolicy:
    """A new set with the policies of both."""
    union = first.subset(range(len(first)))
    for network, info in zip(second.networks, second.infos, strict=True):
        union.add(network, info.weights, info.value, info.agent, info.iteration)
    return union


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a run directory written by sb3-sfgpi train")
    parser.add_argument("--union", metavar="OTHER_RUN", help="compare per test weight with OTHER_RUN and the union")
    args = parser.parse_args(argv)
    run_dir = RunDirectory(args.run_dir)
    config = run_dir.read_config()
    env = load_domain(config["domain"]).make_env(**config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)
    test_weights = np.asarray(config["test_weights"], dtype=np.float64)
    if args.union is not None:
        other = RunDirectory(args.union)
        other_config = other.read_config()
        if other_config["domain"] != config["domain"] or not np.allclose(other_config["test_weights"], test_weights):
            parser.error(f"--union: {args.union} is not a run of the same domain and test weights")
        mine, theirs = final_set(run_dir), final_set(other)
        sets = {args.run_dir: mine, args.union: theirs, "union": joined(mine, theirs)}
        union_per_weight(sets, env, test_weights, gamma, config["seed"])
        env.close()
        return
    state = run_dir.read_checkpoint()
    policy_set = load_policy_set(run_dir, state["n_policies"], iteration=state["iteration"], record=True)
    for iteration in sorted({info.iteration for info in policy_set.infos}):
        subset = policy_set.as_of(iteration).members()  # Π after iteration k
        predicted, returned = predicted_and_returned(subset, env, test_weights, gamma, config["seed"])
        over = predicted - returned
        print(
            f"iteration {iteration}: |Π|={len(subset)}  predicted {predicted.mean():.3f}  "
            f"returned {returned.mean():.3f}  overestimate mean {over.mean():.3f}, largest {over.max():.3f}",
            flush=True,
        )
    env.close()


if __name__ == "__main__":
    main()
