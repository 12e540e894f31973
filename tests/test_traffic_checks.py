"""The claims `examples/traffic.py` prints about a comparison (the README's traffic checks and issue 10's goals)."""

from __future__ import annotations

import pytest
from example_scripts import load_example

traffic_example = load_example("traffic")

VEH, PED = "vehicle_waiting_time_mean", "pedestrian_waiting_time_mean"


def row(method: str, weights, label: str, vehicles: float, pedestrians: float, wg: float | None = None) -> dict:
    metrics = {VEH: {"mean": vehicles, "std": 0.1}, PED: {"mean": pedestrians, "std": 0.1}}
    return {"method": method, "weights": weights, "label": label, "episode_metrics": metrics,
            "scalarized_discounted": wg}  # fmt: skip


def comparison(gpi_vehicles_at_10: float, gpi_wg_at_55: float) -> dict:
    return {
        "rows": [
            row("gpi", [1.0, 0.0], "GPI w=[1,0]", gpi_vehicles_at_10, 20.0, -0.1),
            row("gpi", [0.5, 0.5], "GPI w=[0.5,0.5]", 7.0, 7.0, gpi_wg_at_55),
            row("gpi", [0.0, 1.0], "GPI w=[0,1]", 15.0, 5.0, -0.6),
            row("fixed", [0.5, 0.5], "scalarized w=[0.5,0.5]", 12.0, 5.0, -0.40),
            row("baseline", None, "fixed-time", 10.9, 10.8),
            row("baseline", None, "actuated", 4.5, 14.0),
        ]
    }


def verdicts(compare: dict) -> dict[str, bool]:
    return {claim: holds for claim, holds, _ in traffic_example.checks(compare)}


@pytest.mark.parametrize(("vehicles", "beats_actuated"), [(4.4, True), (4.5, True), (6.8, False)])
def test_gpi_against_actuated_at_1_0(vehicles, beats_actuated):
    claims = verdicts(comparison(vehicles, -0.41))
    assert claims["GPI at w=[1, 0] keeps vehicles waiting no longer than actuated"] is beats_actuated
    assert claims["GPI at w=[1.0, 0.0] beats fixed-time on vehicles"] is (vehicles < 10.9)


@pytest.mark.parametrize(("wg", "within"), [(-0.41, True), (-0.419, True), (-0.43, False), (-0.38, True)])
def test_gpi_within_5_percent_of_the_scalarised_learner(wg, within):
    claims = verdicts(comparison(5.0, wg))
    assert claims["GPI within 5% of the scalarised learner's w·return at w=[0.5, 0.5]"] is within


def test_half_of_fixed_times_pedestrian_waiting_and_the_trade_off():
    claims = verdicts(comparison(5.0, -0.41))
    assert claims["GPI at w=[0, 1] keeps pedestrians waiting at most half as long as fixed-time"]  # 5.0 <= 5.4
    assert claims["GPI pedestrian waiting decreases as w1 grows, w in {[1,0], [0.5,0.5], [0,1]}"]
    assert claims["GPI vehicle waiting increases as w1 grows, w in {[1,0], [0.5,0.5], [0,1]}"]  # 5 -> 7 -> 15 s
