"""The whole SFOLS loop (OLS + SFDQN + GPI) on the paper's Fig. 1 MOMDP, checked against exact optimal values."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import FIG1_TABULAR_STEPS
from momdp import convex_coverage_values, optimal_value, policy_of, policy_value, rollout_return

from sb3_sfgpi.gpi import GPIPolicy
from sb3_sfgpi.ols import OLS

MAX_ITERATIONS = 12


def test_sfols_on_fig1_reaches_the_optimal_value_for_every_weight(make_tabular_sfdqn):
    ols = OLS(2)
    policy_set = GPIPolicy()
    for iteration in range(MAX_ITERATIONS):
        w = ols.next_weight()
        if w is None:
            break
        model = make_tabular_sfdqn(w, seed=iteration)
        model.learn(FIG1_TABULAR_STEPS)
        # γ = 1 and a deterministic env: one greedy rollout is the exact value vector.
        value = rollout_return(lambda obs, model=model: model.predict(obs, deterministic=True)[0])
        np.testing.assert_array_equal(
            value, policy_value(policy_of(lambda s, model=model: model.predict(s, deterministic=True)[0]))
        )
        ols.add_solution(value, w)
        policy_set.add(model, value=value, iteration=iteration)
    assert ols.ended, f"OLS did not end in {MAX_ITERATIONS} iterations (queue: {ols.queue})"
    assert 2 <= len(policy_set) <= MAX_ITERATIONS

    # The set found covers every weight: GPI reaches max_π w · V^π (brute force over all 81 policies).
    for t in np.linspace(0.0, 1.0, 21):
        w = np.array([1.0 - t, t])
        gpi_return = rollout_return(lambda obs, w=w: policy_set.predict(obs, w)[0])
        assert w @ gpi_return == pytest.approx(optimal_value(w), abs=1e-9), f"GPI is suboptimal at w={w}"
    # And OLS's CCS is the true one.
    np.testing.assert_array_equal(np.array(sorted(map(tuple, ols.ccs))), convex_coverage_values())
