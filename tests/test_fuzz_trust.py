"""Fuzzing of what another user's files make this machine do (issue 45): sweep specs (run names, options) and the env
and learner arguments of a shared run's ``run.json`` through ``evaluate``. Every input is taken or refused in one line;
an accepted sweep run trains inside ``--out`` with the sweep's own seed and directory; an evaluated run writes nothing
outside the run directory and the process's temporary directory. ``FUZZ_EXAMPLES=300`` tries 300 fresh examples per
surface; the default run tries the same ones every time.
"""

from __future__ import annotations

import inspect
import json
import os
from pathlib import Path

import pytest
from conftest import tiny_four_room
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from shared_runs import edited

from sb3_sfgpi.cli import main, parse_args
from sb3_sfgpi.cli.sweep_runner import RESERVED_OPTIONS, check_run_name, read_spec
from sb3_sfgpi.sfdqn import SFDQN

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "0"))
FUZZ = settings(
    max_examples=EXAMPLES or 60,
    derandomize=not EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
SLOW_FUZZ = settings(FUZZ, max_examples=EXAMPLES or 25)  # each example may run an episode
JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=8), children, max_size=3),
    max_leaves=6,
)
TRAIN_OPTIONS = ["--iterations", "--env", "--learner", "--set", "--device", "--no-progress", "--budget-from"]
OPTION = st.one_of(
    st.sampled_from([*RESERVED_OPTIONS, *TRAIN_OPTIONS, "-h", "--help", "--"]),
    st.sampled_from([*RESERVED_OPTIONS, *TRAIN_OPTIONS]).flatmap(
        lambda o: st.integers(3, len(o)).map(lambda n: o[:n])  # prefixes: abbreviations
    ),
    st.sampled_from([*RESERVED_OPTIONS, *TRAIN_OPTIONS]).map(lambda o: o + "=/elsewhere"),
    st.text(max_size=6),
)
NAME = st.one_of(
    st.none(),
    st.text(max_size=12),
    st.sampled_from(["/abs/path", "../x", "./r", "r/", "..", ".", "a/../b", "~", "$HOME", "C:\\x", "r\x00"]),
    st.integers(),
)


@FUZZ
@given(name=NAME, options=st.one_of(st.lists(OPTION, max_size=5), JSON), seed=st.integers(0, 9))
@example(name="r", options=["--se", "7", "--ou", "/elsewhere"], seed=0)
@example(name=None, options="--iterations 1", seed=0)
def test_a_sweep_run_trains_inside_out_with_its_own_seed_or_is_refused(tmp_path, name, options, seed):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(
        json.dumps({"runs": [{"domain": "four-room", "seed": seed, "name": name, "options": options}]})
    )

    try:
        (spec,) = read_spec(spec_file)
    except ValueError as error:
        assert "\n" not in str(error)
        return
    out = tmp_path / "out"
    run_dir = out / spec.run_name
    check_run_name(spec.run_name)
    assert run_dir.resolve().parent == out.resolve()  # one component: never outside --out
    try:
        args = parse_args(spec.train_argv(run_dir, resume=False))
    except SystemExit as exited:  # train refuses the options: exit code 2, never a finished run
        assert exited.code == 2
        return
    assert (args.out, args.seed, args.algo, args.resume) == (run_dir, seed, "ma-sfols", False)


@pytest.fixture(scope="module")
def traffic_run(tmp_path_factory) -> Path:
    pytest.importorskip("libsumo")
    out = tmp_path_factory.mktemp("fuzz_trust") / "traffic"
    argv = [
        "train", "traffic", "--env", "num_seconds=20", "--iterations", "1", "--steps-per-iteration", "8",
        "--set", "n_test_weights=1", "--set", "eval_workers=0", "--set", "validation_weights=0",
        "--learner", "learning_starts=0",
        "--learner", "batch_size=4", "--no-progress", "--out", str(out),
    ]  # fmt: skip
    assert main(argv) == 0
    return out


def traffic_arguments() -> list[str]:
    from sfgpi_envs.traffic import TrafficSignalEnv

    return [name for name in inspect.signature(TrafficSignalEnv).parameters if name != "num_seconds"]


#: Values that name files in the watched folder, and SUMO options that write files or run programs.
OUTPUTS = ["--summary-output", "--tripinfo-output", "--fcd-output", "--log", "--save-state.files", "--emission-output"]


def hostile_value(watch: Path) -> st.SearchStrategy:
    victim = str(watch / "victim.xml")
    return st.one_of(
        JSON,
        st.sampled_from(OUTPUTS).map(lambda o: [o, victim]),
        st.sampled_from(OUTPUTS).map(lambda o: [f"{o}={victim}"]),
        st.just(victim),
        st.just([victim]),
        st.just(str(watch / "outputs.add.xml")),
        st.just([str(watch / "outputs.add.xml")]),
        st.just("relative-output.xml"),
    )


@pytest.fixture
def watch(tmp_path, monkeypatch) -> Path:
    """A folder outside the run directory, the working directory of the command: nothing may appear in it."""
    folder = tmp_path / "outside"
    folder.mkdir()
    (folder / "victim.xml").write_text("precious")
    (folder / "outputs.add.xml").write_text(
        f'<additional><edgeData id="x" file="{folder / "written.xml"}" period="5"/></additional>'
    )
    monkeypatch.chdir(folder)
    return folder


def evaluate_shared_run(run: Path, tmp_path: Path, section: str, values: dict, weights: list[str], capsys) -> None:
    copy = edited(run, tmp_path, section, **values)
    before = sorted((p.relative_to(copy), p.stat().st_size) for p in copy.rglob("*") if p.is_file())
    assert main(["evaluate", str(copy), "--w", *weights]) in (0, 2)
    error = capsys.readouterr().err
    assert "Traceback" not in error and len(error.strip().splitlines()) <= 1
    assert sorted((p.relative_to(copy), p.stat().st_size) for p in copy.rglob("*") if p.is_file()) == before


@SLOW_FUZZ
@given(data=st.data())
def test_env_arguments_of_a_shared_run_write_nothing_outside_it(traffic_run, tmp_path, watch, capsys, data):
    keys = data.draw(st.lists(st.sampled_from([*traffic_arguments(), "nonsense"]), min_size=1, max_size=2))
    values = {key: data.draw(hostile_value(watch), label=key) for key in keys}
    evaluate_shared_run(traffic_run, tmp_path, "env_kwargs", values, ["0.5", "0.5"], capsys)
    assert sorted(p.name for p in watch.iterdir()) == ["outputs.add.xml", "victim.xml"]
    assert (watch / "victim.xml").read_text() == "precious"


@pytest.fixture(scope="module")
def four_room_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fuzz_trust") / "four-room"
    argv = [*tiny_four_room(), "--env", "max_steps=30", "--set", "validation_weights=0", "--no-progress"]
    assert main([*argv, "--out", str(out)]) == 0
    return out


@SLOW_FUZZ
@given(data=st.data())
@example(data=None)  # replaced below by a fixed draw: tensorboard_log into the watched folder
def test_learner_arguments_of_a_shared_run_write_nothing_outside_it(four_room_run, tmp_path, watch, capsys, data):
    names = [*inspect.signature(SFDQN).parameters, "nonsense"]
    if data is None:
        values = {"tensorboard_log": str(watch), "gamma": "x"}
    else:
        keys = data.draw(st.lists(st.sampled_from(names), min_size=1, max_size=2))
        values = {key: data.draw(hostile_value(watch), label=key) for key in keys}
    evaluate_shared_run(four_room_run, tmp_path, "learner_kwargs", values, ["1", "0", "0"], capsys)
    assert sorted(p.name for p in watch.iterdir()) == ["outputs.add.xml", "victim.xml"]
