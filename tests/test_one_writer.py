"""Regressions of issue 45, "one writer per run directory": each failed on the code before the fix."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import FEW_VALIDATION, tiny_four_room
from sfgpi_envs import FourRoomParallelEnv

from sb3_sfgpi import MASFOLS
from sb3_sfgpi.cli import main
from sb3_sfgpi.run_directory import RunDirectory, RunDirectoryBusy

TRAIN = [*tiny_four_room(), *FEW_VALIDATION]  # the runs' content does not matter here: who may write them does


def hold_lock(run_dir: Path) -> subprocess.Popen:
    """Another process holding the run directory's lock (as a running `train` does) until it is killed."""
    code = (
        "import sys, time; from sb3_sfgpi.run_directory import RunDirectory; "
        "lock = RunDirectory(sys.argv[1]).lock('sb3-sfgpi train four-room --seed 3'); print('held', flush=True); "
        "time.sleep(120)"
    )
    holder = subprocess.Popen([sys.executable, "-c", code, str(run_dir)], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("writer") / "run"
    assert main([*TRAIN, "--no-progress", "--out", str(out)]) == 0
    return out


def test_a_second_writer_is_refused_naming_the_holder_and_a_killed_holder_leaves_no_stale_lock(tmp_path, capsys):
    out = tmp_path / "run"
    holder = hold_lock(out)
    try:
        assert main([*TRAIN, "--seed", "4", "--no-progress", "--out", str(out)]) == 2
        error = capsys.readouterr().err
        assert f"is being written by another process (pid {holder.pid} on " in error
        assert "sb3-sfgpi train four-room --seed 3" in error and len(error.strip().splitlines()) == 1
        assert sorted(p.name for p in out.iterdir()) == [".lock"]  # nothing written
    finally:
        holder.kill()  # SIGKILL: the kernel releases the lock
        holder.wait()
    assert main([*TRAIN, "--seed", "4", "--no-progress", "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["seed"] == 4


def test_two_resumes_of_one_run_cannot_write_at_once_and_readers_keep_working(finished_run, capsys):
    holder = hold_lock(finished_run)
    try:
        resume = ["train", "four-room", "--iterations", "2", "--no-progress", "--out", str(finished_run), "--resume"]
        assert main(resume) == 2
        assert f"(pid {holder.pid} on " in capsys.readouterr().err
        assert main(["evaluate", str(finished_run), "--w", "1", "0", "0"]) == 0  # readers need no lock
        assert main(["plot", str(finished_run), "--output", str(finished_run.parent / "p.png")]) == 0
    finally:
        holder.kill()
        holder.wait()
    assert json.loads((finished_run / "checkpoint.json").read_text())["iteration"] == 1


def test_the_lock_is_reentrant_in_one_process_and_released_when_dropped(tmp_path):
    run_dir = RunDirectory(tmp_path / "run")
    with run_dir.lock("outer"), run_dir.lock("inner"):
        pass
    lock = run_dir.lock("again")
    lock.release()
    lock.release()  # a no-op
    code = "import sys; from sb3_sfgpi.run_directory import RunDirectory; RunDirectory(sys.argv[1]).lock('x')"
    with run_dir.lock("held"):
        refused = subprocess.run([sys.executable, "-c", code, str(run_dir.path)], capture_output=True, text=True)
        assert RunDirectoryBusy.__name__ in refused.stderr and "held" in refused.stderr
    assert subprocess.run([sys.executable, "-c", code, str(run_dir.path)]).returncode == 0


def sb3_style_folder(path: Path) -> dict[str, bytes]:
    """A folder of someone's SB3 results: progress.csv with 3 rows, an events file, an evaluation.json."""
    (path / "logs").mkdir(parents=True)
    files = {
        "logs/progress.csv": b"time/episodes,rollout/ep_rew_mean\n1,0.5\n2,0.6\n3,0.7\n",
        "logs/events.out.tfevents.1.host": b"\x00\x01events",
        "evaluation.json": b'{"mine": true}',
    }
    for name, data in files.items():
        (path / name).write_bytes(data)
    return files


def test_train_into_a_folder_that_is_not_a_run_of_the_same_settings_is_refused_untouched(tmp_path, finished_run):
    out = tmp_path / "mine"
    files = sb3_style_folder(out)
    argv = ["-m", "sb3_sfgpi.cli", *TRAIN, "--no-progress", "--out", str(out)]
    refused = subprocess.run([sys.executable, *argv], capture_output=True, text=True)
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1
    assert "is not empty and not a run of these settings" in refused.stderr and "nothing was touched" in refused.stderr
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == sorted(files)
    assert all((out / name).read_bytes() == data for name, data in files.items())
    other_seed = subprocess.run(
        [sys.executable, "-m", "sb3_sfgpi.cli", *TRAIN, "--seed", "9", "--out", str(finished_run)],
        capture_output=True,
        text=True,
    )
    assert other_seed.returncode == 2 and "already holds a run: pass --resume" in other_seed.stderr
    assert json.loads((finished_run / "run.json").read_text())["seed"] == 0


def test_a_run_of_the_same_settings_killed_before_its_first_checkpoint_may_be_trained_again(finished_run):
    settings = json.loads((finished_run / "run.json").read_text())
    same = {key: settings[key] for key in ("domain", "algorithm", "seed", "weights", "env_kwargs")}
    RunDirectory(finished_run).check_new_run(same)  # train then refuses it only for its checkpoint (--resume)
    with pytest.raises(ValueError, match="not a run of these settings"):
        RunDirectory(finished_run).check_new_run({**same, "seed": 1})


@pytest.mark.parametrize(
    "argv",
    [["--env", "nosuchkey=1"], ["--learner", "bogus=1"], ["--set", "eval_workers=-1"], ["--resume"]],
    ids=["env", "learner", "workers", "resume-nothing"],
)
def test_a_refused_train_leaves_no_directory_behind(tmp_path, argv):
    out = tmp_path / "new"
    assert main([*TRAIN, "--no-progress", "--out", str(out), *argv]) == 2
    assert not out.exists()


def test_masfols_learn_holds_the_lock_too(tmp_path):
    """The API's writer is refused as the command line's is, and writes nothing."""
    out = tmp_path / "run"
    holder = hold_lock(out)
    try:
        model = MASFOLS(
            FourRoomParallelEnv(max_steps=30),
            steps_per_iteration=100,
            test_weights=2,
            run_dir=out,
        )
        with pytest.raises(RunDirectoryBusy, match=f"pid {holder.pid} on "):
            model.learn(max_iterations=1)
        assert sorted(p.name for p in out.iterdir()) == [".lock"]
    finally:
        holder.kill()
        holder.wait()
    model.learn(max_iterations=1)
    assert RunDirectory(out).read_checkpoint()["iteration"] == 1
