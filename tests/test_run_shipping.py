"""Run directories sent home (``sweep --no-shared-filesystem``): snapshots as of one checkpoint, unpacked safely."""

from __future__ import annotations

import io
import tarfile

import pytest
from conftest import train_tiny_run

from sb3_sfgpi.cli import run_shipping
from sb3_sfgpi.cli.run_shipping import snapshot, unpack
from sb3_sfgpi.run_directory import RunDirectory
from sb3_sfgpi.run_policy_set import load_policy_set


def files(folder) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_snapshot_unpacks_into_the_same_run_directory_but_its_lock(tmp_path):
    run = train_tiny_run(tmp_path / "run")
    (run / ".lock").write_text("{}")  # a writer's lock stays on its node
    home = tmp_path / "home" / "run"
    unpack(snapshot(run), home)
    assert files(home) == {name: data for name, data in files(run).items() if name != ".lock"}
    assert load_policy_set(RunDirectory(home)) is not None  # the checkpoint's Π
    (run / "evaluation.csv").write_text("changed")
    unpack(snapshot(run), home)  # a later snapshot replaces the earlier one
    assert (home / "evaluation.csv").read_text() == "changed"
    assert sorted(p.name for p in home.parent.iterdir()) == ["run"]  # nothing left beside it


def test_a_snapshot_is_taken_again_while_the_checkpoint_changes(tmp_path, monkeypatch):
    run = train_tiny_run(tmp_path / "run")
    tar, calls = run_shipping._tar, []

    def checkpoint_written_meanwhile(run_dir):
        calls.append(1)
        data = tar(run_dir)
        if len(calls) == 1:
            (run_dir / "checkpoint.json").write_text((run_dir / "checkpoint.json").read_text() + " ")
        return data

    monkeypatch.setattr(run_shipping, "_tar", checkpoint_written_meanwhile)
    unpack(snapshot(run), tmp_path / "home")
    assert len(calls) == 2 and files(tmp_path / "home")["checkpoint.json"] == (run / "checkpoint.json").read_bytes()

    def always_written(run_dir):
        (run_dir / "checkpoint.json").write_text((run_dir / "checkpoint.json").read_text() + " ")
        return b""

    monkeypatch.setattr(run_shipping, "_tar", always_written)
    with pytest.raises(RuntimeError, match="the checkpoint changed during 20 snapshots"):
        snapshot(run)


def archive(*members: tarfile.TarInfo) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tar:
        for member in members:
            tar.addfile(member, io.BytesIO(b"x" * member.size))
    return buffer.getvalue()


def member(name: str, kind: bytes = tarfile.REGTYPE, target: str = "") -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.linkname, info.size = kind, target, 1 if kind == tarfile.REGTYPE else 0
    return info


@pytest.mark.parametrize(
    "bad",
    [
        member("../outside"),
        member("/etc/passwd"),
        member("policy_set/../../outside"),
        member("link", tarfile.SYMTYPE, "/etc/passwd"),
        member("hard", tarfile.LNKTYPE, "run.json"),
        member("folder", tarfile.DIRTYPE),
        member(".lock"),
    ],
)
def test_unpack_refuses_anything_but_plain_files_inside_the_run(tmp_path, bad):
    home = tmp_path / "home" / "run"
    with pytest.raises(ValueError, match="only plain files inside the run"):
        unpack(archive(member("run.json"), bad), home)
    assert not home.exists() and not (tmp_path / "outside").exists()
