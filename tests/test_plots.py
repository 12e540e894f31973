"""The figures: GPI return over iterations from run directories, and the comparison plots from a comparison dict."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from example_scripts import load_example
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_sfgpi import plots
from sb3_sfgpi.cli import main
from sb3_sfgpi.cli.compare import merge_comparisons
from sb3_sfgpi.cli.plot import final_test_returns, own_weight_return
from sb3_sfgpi.run_directory import RunDirectory

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
STEP_METRICS = [["vehicle_wait_total", "vehicle waiting time [s]"], ["pedestrian_wait_total", "pedestrian wait [s]"]]
EPISODE_METRICS = [["vehicle_mean", "mean vehicle waiting time [s]"], ["pedestrian_mean", "mean pedestrian wait [s]"]]
TIME = [5.0, 10.0, 15.0, 20.0, 25.0, 30.0]


@pytest.fixture
def figures(monkeypatch) -> list[dict]:
    """What every figure saved shows: per axes its labels, title and lines (the real ``_save`` still writes)."""
    seen: list[dict] = []
    real_save = plots._save

    def recording(fig, output):
        axes = [
            {
                "xlabel": ax.get_xlabel(),
                "ylabel": ax.get_ylabel(),
                "title": ax.get_title(),
                "ylim": ax.get_ylim(),
                "lines": [(line.get_label(), line.get_xydata().copy()) for line in ax.get_lines()],
                "styles": [(line.get_label(), line.get_linestyle(), line.get_marker()) for line in ax.get_lines()],
                "legend": [text.get_text() for text in ax.get_legend().get_texts()] if ax.get_legend() else [],
            }
            for ax in fig.axes
        ]
        seen.append({"output": output, "axes": axes})
        return real_save(fig, output)

    monkeypatch.setattr(plots, "_save", recording)
    return seen


def summary_row(i: int, value: float, hypervolume: float | None = None) -> dict:
    """The summary row of iteration ``i`` with GPI's mean return ``value``."""
    return {
        "iteration": i,
        "timesteps": 100 * (i + 1),
        "n_policies": i + 1,
        "ccs_size": i + 1,
        "mean_return": value,
        "mean_return_undiscounted": value,
        "expected_utility": value,
        "hypervolume": hypervolume,
        "wall_time": float(i),
        "eval_time": 0.1,
    }


def write_run(path, mean_returns, hypervolumes=None, ols_ended=True) -> RunDirectory:
    run_dir = RunDirectory(path)
    run_dir.write_config({"domain": "four-room", "algorithm": "ma-sfols"})
    history = [
        summary_row(i, value, None if hypervolumes is None else hypervolumes[i]) for i, value in enumerate(mean_returns)
    ]
    next_weights = None if ols_ended else {"agent_0": [0.5, 0.5]}
    checkpoint = {"iteration": len(history), "timesteps": 0, "n_policies": 0, "schedule": {"ols": {}}}
    run_dir.write_iteration(history, {**checkpoint, "next_weights": next_weights})
    return run_dir


def assert_png(path) -> None:
    assert path.is_file() and path.read_bytes()[:8] == PNG_MAGIC


# --- plot_returns -----------------------------------------------------------------------------------------------
def test_plot_returns_draws_the_mean_over_seeds_with_labelled_axes(tmp_path, figures):
    long = write_run(tmp_path / "a", [1.0, 2.0, 3.0])
    short = write_run(tmp_path / "b", [3.0, 4.0])  # ended after two iterations: keeps 4.0 at iteration 3
    other = write_run(tmp_path / "c", [0.5, 0.5, 1.5])
    output = tmp_path / "figs" / "returns.png"
    result = plots.plot_returns([("ma-sfols", long), ("ma-sfols", short), ("random", other)], output)
    assert result == output
    assert_png(output)
    (figure,) = figures
    (ax,) = figure["axes"]
    assert ax["xlabel"] == "iteration" and ax["ylabel"] == "w·(discounted return), mean"
    assert ax["title"] == "GPI over the policy set, mean over test weights and agents"
    assert ax["legend"] == ["MA-SFOLS + GPI (2 seeds)", "Random + GPI (1 seed)"]
    lines = dict(ax["lines"])
    np.testing.assert_allclose(lines["MA-SFOLS + GPI (2 seeds)"], [[1, 2.0], [2, 3.0], [3, 3.5]])
    np.testing.assert_allclose(lines["Random + GPI (1 seed)"], [[1, 0.5], [2, 0.5], [3, 1.5]])


def test_plot_returns_of_another_metric_skips_empty_cells(tmp_path, figures):
    run = write_run(tmp_path / "a", [1.0, 2.0, 3.0], hypervolumes=[None, 10.0, 12.0])
    output = plots.plot_returns([("fixed", run)], tmp_path / "hv.png", metric="hypervolume", title="my title")
    assert_png(output)
    (ax,) = figures[0]["axes"]
    assert (ax["xlabel"], ax["ylabel"], ax["title"]) == ("iteration", "hypervolume", "my title")
    np.testing.assert_allclose(ax["lines"][0][1], [[2, 10.0], [3, 12.0]])
    assert ax["legend"] == ["fixed-weight learners (1 seed)"]


def test_plot_returns_draws_reference_lines(tmp_path, figures):
    run = write_run(tmp_path / "a", [1.0, 2.0])
    references = [plots.Reference("a priori", 1.5, 0.1), plots.Reference("exact optimum", 2.5)]
    plots.plot_returns([("ma-sfols", run)], tmp_path / "r.png", references=references)
    (ax,) = figures[0]["axes"]
    lines = dict(ax["lines"])
    assert lines["a priori"][:, 1].tolist() == [1.5, 1.5] and lines["exact optimum"][:, 1].tolist() == [2.5, 2.5]
    assert ax["legend"] == ["MA-SFOLS + GPI (1 seed)", "a priori", "exact optimum"]


def write_fixed_run(path, w, seed, at_w, elsewhere=0.0) -> RunDirectory:
    """A fixed-weight run for ``w``, evaluated at ``w`` (discounted returns ``at_w`` of its two agents, per
    objective) and at one other test weight."""
    run_dir = RunDirectory(path)
    run_dir.write_config({"domain": "four-room", "algorithm": "fixed", "seed": seed, "weights": w})
    test = [
        {"weights": [1.0, 0.0], "agents": {"a": {"discounted": [elsewhere, 0.0]}, "b": {"discounted": [elsewhere, 0]}}},
        {"weights": w, "agents": {"a": {"discounted": at_w[0]}, "b": {"discounted": at_w[1]}}},
    ]
    run_dir.write_iteration(
        [{**summary_row(0, 0.0), "test": test}],
        {"iteration": 1, "timesteps": 0, "n_policies": 1, "schedule": {"ols": {}}},
    )
    return run_dir


def test_plot_fixed_runs_draw_the_a_priori_learners_at_their_own_weights(tmp_path, figures):
    run = write_run(tmp_path / "ols", [1.0, 2.0])
    fixed = [
        write_fixed_run(tmp_path / "f0", [0.5, 0.5], 0, ([2.0, 0.0], [0.0, 2.0])),  # 1.0 at its weight
        write_fixed_run(tmp_path / "f1", [0.0, 1.0], 0, ([0.0, 3.0], [9.0, 1.0]), elsewhere=50.0),  # 2.0
        write_fixed_run(tmp_path / "f2", [0.5, 0.5], 1, ([4.0, 0.0], [4.0, 0.0])),  # 2.0
        write_fixed_run(tmp_path / "f3", [0.0, 1.0], 1, ([0.0, 4.0], [0.0, 4.0])),  # 4.0
    ]
    argv = ["plot", str(run.path), "-o", str(tmp_path / "r.png"), "--reference", "exact optimum=3.25"]
    assert main([*argv, "--fixed", *(str(f.path) for f in fixed)]) == 0
    (ax,) = figures[0]["axes"]
    label = "learners trained a priori (4 runs, 2 seeds)"
    assert ax["legend"] == ["MA-SFOLS + GPI (1 seed)", label, "exact optimum"]
    lines = dict(ax["lines"])
    assert lines[label][0, 1] == pytest.approx((1.5 + 3.0) / 2) and lines["exact optimum"][0, 1] == 3.25


def test_final_test_returns_average_the_agents_and_own_weight_return_reads_the_runs_weight(tmp_path):
    run = write_fixed_run(tmp_path / "f", [0.25, 0.75], 0, ([2.0, 0.0], [0.0, 4.0]), elsewhere=6.0)
    (w0, v0), (w1, v1) = final_test_returns(run)
    assert (w0.tolist(), v0.tolist()) == ([1.0, 0.0], [6.0, 0.0])
    assert (w1.tolist(), v1.tolist()) == ([0.25, 0.75], [1.0, 2.0])
    w, value = own_weight_return(run)
    assert w.tolist() == [0.25, 0.75] and value == pytest.approx(0.25 * 1.0 + 0.75 * 2.0)


def test_the_four_room_example_prints_gpi_beside_the_a_priori_learners_per_weight(tmp_path, capsys):
    example = load_example("four_room")
    gpi = [write_fixed_run(tmp_path / f"g{s}", [0.5, 0.5], s, ([r, r], [r, r])) for s, r in ((0, 1.0), (1, 3.0))]
    apriori = [write_fixed_run(tmp_path / f"f{s}", [0.5, 0.5], s, ([1.0, 1.0], [1.0, 1.0])) for s in (0, 1)]
    example.print_per_weight([run.path for run in gpi], [run.path for run in apriori], "random")
    rows = capsys.readouterr().out.strip().splitlines()
    assert rows[0] == "| test weight | random + GPI, final | a priori | ratio |" and len(rows) == 3
    assert rows[-1] == "| [0.5,0.5] | 2.000 ± 1.000 | 1.000 ± 0.000 | 2.000 |"


def test_the_four_room_examples_a_priori_runs_take_the_runs_sharing_and_env_not_their_schedule():
    example = load_example("four_room")
    args = argparse.Namespace(iterations=4, steps_per_iteration=100, apriori_seeds=[0], sharing="shared")
    extra = ["--env=max_steps=50", "--iterations", "4", "--steps-per-iteration", "100", "--set", "sharing=shared"]
    specs = example.apriori_specs(args, extra)
    assert len(specs) == 12 and all(spec.algo == "fixed" for spec in specs)
    assert specs[0].options == (
        "--env=max_steps=50",
        "--set",
        "sharing=shared",
        "--iterations",
        "1",
        "--steps-per-iteration",
        "400",
    )


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--reference", "optimum"], "--reference expects LABEL=NUMBER, got 'optimum'"),
        (["--reference", "optimum=high"], "--reference expects LABEL=NUMBER"),
        (["--reference", "=1.0"], "--reference expects LABEL=NUMBER"),
        (["--fixed", "OLS"], "is not a run of `train --algo fixed`"),
        (["--fixed", "FIXED", "--metric", "hypervolume"], "--fixed draws the a-priori learners' mean_return"),
        (["--fixed", "ELSEWHERE"], "was not evaluated at its own weight"),
    ],
)
def test_plot_refuses_bad_references(tmp_path, capsys, extra, message):
    run = write_run(tmp_path / "ols", [1.0])
    write_fixed_run(tmp_path / "fixed", [0.5, 0.5], 0, ([1.0, 1.0], [1.0, 1.0]))
    elsewhere = write_fixed_run(tmp_path / "elsewhere", [0.3, 0.7], 0, ([1.0, 1.0], [1.0, 1.0]))
    elsewhere.write_config({"domain": "four-room", "algorithm": "fixed", "seed": 0, "weights": [0.9, 0.1]})
    paths = {"OLS": run.path, "FIXED": tmp_path / "fixed", "ELSEWHERE": elsewhere.path}
    extra = [str(paths.get(item, item)) for item in extra]
    assert main(["plot", str(run.path), "-o", str(tmp_path / "r.png"), *extra]) == 2
    assert message in capsys.readouterr().err


def test_plot_returns_needs_evaluations(tmp_path):
    with pytest.raises(ValueError, match="no evaluation.csv"):
        plots.plot_returns([("ma-sfols", RunDirectory(tmp_path))], tmp_path / "x.png")


# --- comparison plots -------------------------------------------------------------------------------------------
def trace(level: float, slope: float) -> dict:
    mean = [level + slope * t for t in range(len(TIME))]
    return {"mean": mean, "std": [0.5] * len(TIME)}


def compare_row(method: str, weights, label: str, vehicles: float, pedestrians: float) -> dict:
    return {
        "method": method,
        "label": label,
        "run_dir": None,
        "weights": weights,
        "return_discounted": [-vehicles, -pedestrians],
        "return_undiscounted": [-vehicles, -pedestrians],
        "scalarized_discounted": None if weights is None else -float(np.dot(weights, [vehicles, pedestrians])),
        "agents": {},
        "episode_metrics": {
            "vehicle_mean": {"mean": vehicles, "std": 1.0},
            "pedestrian_mean": {"mean": pedestrians, "std": 2.0},
        },
        "traces": {
            "time": TIME,
            "vehicle_wait_total": trace(vehicles, 1.0),
            "pedestrian_wait_total": trace(pedestrians, -1.0),
        },
    }


@pytest.fixture
def compare() -> dict:
    """A small comparison in the format of ``sb3-sfgpi compare`` (see :mod:`sb3_sfgpi.cli.compare`)."""
    return {
        "format": "sb3-sfgpi/compare",
        "version": 1,
        "domain": "traffic",
        "objectives": ["vehicles", "pedestrians"],
        "episode_metrics": EPISODE_METRICS,
        "step_metrics": STEP_METRICS,
        "rows": [
            compare_row("gpi", [1.0, 0.0], "GPI w=[1, 0]", 10.0, 40.0),
            compare_row("gpi", [0.5, 0.5], "GPI w=[0.5, 0.5]", 20.0, 20.0),
            compare_row("gpi", [0.0, 1.0], "GPI w=[0, 1]", 40.0, 10.0),
            compare_row("fixed", [0.5, 0.5], "scalarized w=[0.5, 0.5]", 22.0, 21.0),
            compare_row("baseline", None, "fixed-time", 30.0, 30.0),
        ],
    }


def test_plot_step_metrics_draws_every_objective_and_its_zoom(tmp_path, compare, figures):
    written = plots.plot_step_metrics(compare, tmp_path / "steps", smooth=1)
    names = ["steps_vehicles.png", "steps_vehicles_zoom.png", "steps_pedestrians.png", "steps_pedestrians_zoom.png"]
    assert [p.name for p in written] == names
    for path in written:
        assert_png(path)
    zoomed = [False, True, False, True]
    for figure, (_, label), zoom in zip(figures, [STEP_METRICS[0]] * 2 + [STEP_METRICS[1]] * 2, zoomed, strict=True):
        (ax,) = figure["axes"]
        assert ax["xlabel"] == "simulated time [s]"
        assert ax["ylabel"] == label  # smooth=1: the raw metric
        assert label.split(" [")[0] in ax["title"]
        # one curve per GPI weight (the zoom: those favouring the objective), none for the fixed learner or baseline
        assert len(ax["lines"]) == (2 if zoom else 3)
        for _, xy in ax["lines"]:
            np.testing.assert_allclose(xy[:, 0], TIME)
    # Curves are in the order of the objective's weight, labelled by the whole weight vector.
    assert figures[0]["axes"][0]["legend"] == ["w = [0,1]", "w = [0.5,0.5]", "w = [1,0]"]
    assert figures[2]["axes"][0]["legend"] == ["w = [1,0]", "w = [0.5,0.5]", "w = [0,1]"]
    # The zoom on vehicles shows only the curves with w0 >= 0.5 (levels 10 and 20, rising by 1 per step).
    assert figures[1]["axes"][0]["legend"] == ["w = [0.5,0.5]", "w = [1,0]"]
    assert "only weights with vehicles ≥ 0.5" in figures[1]["axes"][0]["title"]
    assert "only" not in figures[0]["axes"][0]["title"]


def test_plot_step_metrics_smoothing_is_named_in_the_label(tmp_path, compare, figures):
    plots.plot_step_metrics(compare, tmp_path, smooth=2)
    assert figures[0]["axes"][0]["ylabel"] == "vehicle waiting time [s], mean over 10 s"
    first = figures[0]["axes"][0]["lines"][0][1][:, 1]  # w0 = 0: level 40, rising by 1
    np.testing.assert_allclose(first, [40.0, 40.5, 41.5, 42.5, 43.5, 44.5])


def test_plot_versus_draws_gpi_against_each_fixed_learner_per_objective(tmp_path, compare, figures):
    written = plots.plot_versus(compare, tmp_path / "versus", smooth=1)
    assert [p.name for p in written] == ["versus_w0.5-0.5.png"]
    assert_png(written[0])
    (figure,) = figures
    assert len(figure["axes"]) == 2  # one panel per objective
    for ax, (_, label), name in zip(figure["axes"], STEP_METRICS, ["vehicles", "pedestrians"], strict=True):
        assert ax["xlabel"] == "simulated time [s]" and ax["ylabel"] == label
        assert ax["title"] == f"w = [0.5,0.5] ({name})"
        assert ax["legend"] == ["MA-SFOLS + GPI", "scalarized w=[0.5, 0.5]", "fixed-time"]
    gpi_vehicles = dict(figure["axes"][0]["lines"])["MA-SFOLS + GPI"]
    np.testing.assert_allclose(gpi_vehicles[:, 1], trace(20.0, 1.0)["mean"])


def test_plot_tradeoff_puts_the_two_episode_metrics_on_the_axes(tmp_path, compare, figures):
    output = plots.plot_tradeoff(compare, tmp_path / "tradeoff.png")
    assert_png(output)
    ax, colorbar = figures[0]["axes"]  # GPI's points are coloured by their weight
    assert "weight w0 of vehicles" in colorbar["ylabel"]
    assert ax["xlabel"] == EPISODE_METRICS[0][1] and ax["ylabel"] == EPISODE_METRICS[1][1]
    assert ax["legend"] == ["MA-SFOLS + GPI", "scalarized w=[0.5, 0.5]", "fixed-time"]
    gpi = ax["lines"][0][1]  # errorbar's data line (the label is its container's); in the order of w
    np.testing.assert_allclose(gpi, [[40.0, 10.0], [20.0, 20.0], [10.0, 40.0]])
    points = {tuple(xy[0]) for _, xy in ax["lines"] if len(xy) == 1}  # the other methods: one marker each
    assert {(22.0, 21.0), (30.0, 30.0)} <= points


def test_three_baselines_are_drawn_apart(tmp_path, compare, figures):
    names = ["fixed-time", "actuated", "max-pressure"]
    rows = compare["rows"][:-1] + [compare_row("baseline", None, n, 30.0 + i, 30.0 - i) for i, n in enumerate(names)]
    compare = {**compare, "rows": rows}
    plots.plot_versus(compare, tmp_path, smooth=1)
    plots.plot_tradeoff(compare, tmp_path / "tradeoff.png")
    versus, tradeoff = figures[0]["axes"][0], figures[1]["axes"][0]
    assert versus["legend"][-3:] == tradeoff["legend"][-3:] == names
    styles = {label: style for label, style, _ in versus["styles"] if label in names}
    assert len(set(styles.values())) == 3 and "-" not in styles.values()  # dashed, dash-dotted, dotted
    caps = ("|", "_")  # the error bars' ends
    points = [m for (_, _, m), (_, xy) in zip(tradeoff["styles"], tradeoff["lines"], strict=True) if len(xy) == 1]
    points = [m for m in points if m not in caps]
    assert len(points) == len(set(points)) == 4  # the learner and each baseline: a marker of its own


def test_comparison_plots_refuse_what_they_cannot_draw(tmp_path, compare):
    no_fixed = {**compare, "rows": [r for r in compare["rows"] if r["method"] != "fixed"]}
    with pytest.raises(ValueError, match="no fixed-weight learners"):
        plots.plot_versus(no_fixed, tmp_path)
    no_gpi = {**compare, "rows": [r for r in compare["rows"] if r["method"] != "gpi"]}
    with pytest.raises(ValueError, match="no GPI rows"):
        plots.plot_step_metrics(no_gpi, tmp_path)
    with pytest.raises(ValueError, match="two episode metrics"):
        plots.plot_tradeoff({**compare, "episode_metrics": EPISODE_METRICS[:1]}, tmp_path / "x.png")
    no_trace = {**compare, "step_metrics": [["queue", "queue length"]]}
    with pytest.raises(ValueError, match="no per-step 'queue'"):
        plots.plot_step_metrics(no_trace, tmp_path)
    assert not list(tmp_path.glob("*.png"))


def shifted(compare: dict, by: float) -> dict:
    """The comparison of another training seed: every mean ``by`` higher, the same stds."""
    rows = []
    for row in compare["rows"]:
        metrics = {k: {**m, "mean": m["mean"] + by} for k, m in row["episode_metrics"].items()}
        traces = {k: v if k == "time" else {**v, "mean": [x + by for x in v["mean"]]} for k, v in row["traces"].items()}
        scalarized = None if row["weights"] is None else row["scalarized_discounted"] + by
        rows.append({**row, "episode_metrics": metrics, "traces": traces, "scalarized_discounted": scalarized})
    return {**compare, "run_dir": f"seed shifted by {by}", "rows": rows}


def test_comparisons_of_several_seeds_merge_into_means_and_pooled_stds(compare):
    merged = merge_comparisons([shifted(compare, 0.0), shifted(compare, 2.0), shifted(compare, 4.0)])
    assert merged["merged"] == 3 and len(merged["rows"]) == len(compare["rows"])
    gpi = merged["rows"][0]
    assert gpi["episode_metrics"]["vehicle_mean"]["mean"] == pytest.approx(12.0)
    # pooled over the 3 x n episodes: within-seed std 1, seed means 10, 12, 14 (population variance 8/3)
    assert gpi["episode_metrics"]["vehicle_mean"]["std"] == pytest.approx(np.sqrt(1.0 + 8 / 3))
    np.testing.assert_allclose(gpi["traces"]["vehicle_wait_total"]["mean"], np.array(trace(12.0, 1.0)["mean"]))
    np.testing.assert_allclose(gpi["traces"]["vehicle_wait_total"]["std"], np.sqrt(0.25 + 8 / 3))
    assert gpi["traces"]["time"] == TIME
    assert gpi["scalarized_discounted"] == pytest.approx(-10.0 + 2.0)
    assert gpi["scalarized_discounted_std"] == pytest.approx(np.sqrt(8 / 3))
    assert merged["rows"][-1]["scalarized_discounted_std"] is None  # a baseline has no weights


def test_comparisons_merge_row_by_row_whatever_their_order(compare):
    reordered = {**shifted(compare, 2.0), "rows": shifted(compare, 2.0)["rows"][::-1]}
    merged = merge_comparisons([shifted(compare, 0.0), reordered])
    assert [row["label"] for row in merged["rows"]] == [row["label"] for row in compare["rows"]]
    assert merged["rows"][3]["episode_metrics"]["vehicle_mean"]["mean"] == pytest.approx(23.0)  # the fixed learner


def test_comparisons_of_other_methods_or_settings_are_not_merged(compare, tmp_path, capsys):
    fewer = {**compare, "rows": compare["rows"][1:]}
    with pytest.raises(ValueError, match="different methods or weights"):
        merge_comparisons([compare, fewer])
    with pytest.raises(ValueError, match="differ in 'episodes'"):
        merge_comparisons([{**compare, "episodes": 5}, {**compare, "episodes": 3}])
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for path, data in zip(paths, [compare, fewer], strict=True):
        path.write_text(json.dumps(data))
    assert main(["plot", *map(str, paths), "--kind", "steps", "-o", str(tmp_path / "figs")]) == 2
    assert "cannot draw" in capsys.readouterr().err


def test_plot_draws_several_comparison_files_as_one(compare, tmp_path, figures):
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for path, by in zip(paths, [0.0, 2.0], strict=True):
        path.write_text(json.dumps(shifted(compare, by)))
    assert main(["plot", *map(str, paths), "--kind", "tradeoff", "-o", str(tmp_path / "t.png")]) == 0
    ax = figures[0]["axes"][0]
    assert ax["title"] == "per-objective outcome (mean ± std over the episodes of 2 runs)"
    np.testing.assert_allclose(ax["lines"][0][1], [[41.0, 11.0], [21.0, 21.0], [11.0, 41.0]])  # in the order of w


def test_a_seed_that_stopped_early_is_not_drawn_as_if_it_went_on(tmp_path, figures):
    runs = [
        ("ma-sfols", write_run(tmp_path / "a", [1.0, 2.0, 3.0])),
        ("ma-sfols", write_run(tmp_path / "b", [3.0], ols_ended=False)),  # interrupted after iteration 1
        ("ma-sfols", write_run(tmp_path / "c", [2.0, 5.0])),  # OLS ended: its set stays as it was
    ]
    plots.plot_returns(runs, tmp_path / "r.png")
    (ax,) = figures[0]["axes"]
    np.testing.assert_allclose(ax["lines"][0][1][:, 1], [2.0, 3.5, 4.0])  # b counts at iteration 1 only
    assert ax["legend"] == ["MA-SFOLS + GPI (3 seeds, 2 from iteration 2)"]


# --- align_runs and moving_average ------------------------------------------------------------------------------
def test_align_runs_forward_fills_runs_that_ended_early():
    values = plots.align_runs([{1: 1.0, 2: 2.0, 3: 5.0}, {1: 3.0}, {1: 0.0, 2: -1.0}])
    np.testing.assert_allclose(values, [[1.0, 2.0, 5.0], [3.0, 3.0, 3.0], [0.0, -1.0, -1.0]])


@settings(max_examples=50, deadline=None)
@given(st.lists(st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=8), min_size=1, max_size=5))
def test_align_runs_keeps_each_run_and_then_its_last_value(runs):
    aligned = plots.align_runs([{i + 1: v for i, v in enumerate(run)} for run in runs])
    longest = max(len(run) for run in runs)
    assert aligned.shape == (len(runs), longest)
    for row, run in zip(aligned, runs, strict=True):
        np.testing.assert_array_equal(row, run + [run[-1]] * (longest - len(run)))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), max_size=30), st.integers(-1, 12))
def test_moving_average_is_the_trailing_mean(values, window):
    smoothed = plots.moving_average(np.array(values), window)
    assert smoothed.shape == (len(values),)
    for i in range(len(values)):
        expected = values[i] if window <= 1 else np.mean(values[max(0, i + 1 - window) : i + 1])
        assert smoothed[i] == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize(
    ("output", "kind", "message"),
    [
        ("missing/dir/x.png", "returns", "the directory"),
        ("existing_dir", "returns", "writes one .png file"),
        ("x.pdf", "returns", "writes one .png file"),
        ("a_file.png", "steps", "is a file"),
    ],
)
def test_plot_writes_exactly_where_asked_or_refuses(tmp_path, capsys, output, kind, message):
    run = write_run(tmp_path / "ols", [1.0])
    (tmp_path / "existing_dir").mkdir()
    (tmp_path / "a_file.png").write_bytes(b"")
    assert main(["plot", str(run.path), "-o", str(tmp_path / output), "--kind", kind]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "missing").exists() and not (tmp_path / "existing_dir.png").exists()
