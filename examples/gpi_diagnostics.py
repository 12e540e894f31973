"""GPI's own estimate against its return, iteration by iteration, for a finished MA-SFOLS run.

For every iteration ``k`` of the run, Π is cut to what it was after iteration ``k`` (the policies of iterations
``1..k`` that validation had not retired by then) and, for every test weight of the run and every agent, two numbers
are compared:

* predicted: ``max_π max_a w · ψπ(s0, a)``, the value GPI expects from the agent's first observation;
* returned: ``w · (discounted return)`` of the agents acting by GPI (the run's evaluation episode seeds).

With exact successor features the return is at least the prediction (GPI's theorem). A prediction above the return
is an overestimate: some policy's ψ is wrong where GPI follows it. The script prints the means over test weights and
agents and the largest overestimate.

Run: ``python examples/gpi_diagnostics.py RUN_DIR`` (e.g. a run of ``sb3-sfgpi train four-room``)
"""

from __future__ import annotations

import argparse

import numpy as np

from sb3_sfgpi.cli.presets import load_domain
from sb3_sfgpi.common.rollouts import run_episodes
from sb3_sfgpi.common.seeding import derive_seed
from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.run_directory import RunDirectory


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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a run directory written by sb3-sfgpi train")
    args = parser.parse_args(argv)
    run_dir = RunDirectory(args.run_dir)
    config = run_dir.read_config()
    state = run_dir.read_checkpoint()
    policy_set = run_dir.load_policy_set(state["n_policies"], iteration=state["iteration"], record=True)
    env = load_domain(config["domain"]).make_env(**config["env_kwargs"])
    gamma = config["learner_kwargs"].get("gamma", 0.99)
    test_weights = np.asarray(config["test_weights"], dtype=np.float64)
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
