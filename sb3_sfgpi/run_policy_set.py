"""Π in a run directory: staged by an iteration, committed by its checkpoint, read as of a checkpoint.

An iteration writes its Π beside the committed one (``policy_set/manifest.next.json``, its files stamped with the
iteration, so that no committed file is written over); its checkpoint names it by the digest of that manifest
(:func:`staged_digest`); then :func:`commit_policy_set` makes it ``manifest.json`` and removes the files no manifest
names. :func:`load_policy_set` reads the set the checkpoint names wherever its writer stopped: a reader never sees a
set that no checkpoint had. Importing this module imports neither torch nor Stable-Baselines3.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import TYPE_CHECKING

from sb3_sfgpi.common.serialization import read_json
from sb3_sfgpi.run_directory import MANIFEST, STAGED_MANIFEST, RunDirectory

if TYPE_CHECKING:
    import torch as th

    from sb3_sfgpi.gpi import GPIPolicy


def stage_policy_set(run_dir: RunDirectory, policy_set: GPIPolicy, iteration: int) -> Path:
    """
    Write the set an iteration makes beside the committed one, for its checkpoint to name.

    :param iteration: the iteration (stamped in its files' names)
    :return: its manifest (what evaluation workers load)
    """
    policy_set.save(run_dir.policy_set_dir, manifest=STAGED_MANIFEST, stamp=iteration)
    _remove_unlisted_files(run_dir.policy_set_dir)
    return run_dir.policy_set_dir / STAGED_MANIFEST


def staged_digest(run_dir: RunDirectory) -> str | None:
    """What a checkpoint names its Π by: the digest of the staged manifest, else of the committed one (None: none)."""
    for name in (STAGED_MANIFEST, MANIFEST):
        if (run_dir.policy_set_dir / name).is_file():
            return _digest(run_dir.policy_set_dir / name)
    return None


def commit_policy_set(run_dir: RunDirectory) -> None:
    """
    Make the staged set the run's set if the checkpoint names it, else drop it; then remove the files no manifest
    names (after every checkpoint, and before a resumed run goes on).
    """
    staged = run_dir.policy_set_dir / STAGED_MANIFEST
    if staged.is_file():
        if _is_named(staged, _named(run_dir)):
            staged.replace(run_dir.policy_set_dir / MANIFEST)
        else:
            staged.unlink()
    _remove_unlisted_files(run_dir.policy_set_dir)


def policy_set_manifest(run_dir: RunDirectory) -> Path | None:
    """
    The manifest of the checkpoint's Π: the committed one, or the staged one the checkpoint named if its writer
    stopped before committing it (None: no set yet; without a checkpoint, a saved set's manifest).

    :raises ValueError: neither manifest is the one the checkpoint names
    """
    committed, staged = run_dir.policy_set_dir / MANIFEST, run_dir.policy_set_dir / STAGED_MANIFEST
    named = _named(run_dir)
    if named is None:
        return committed if committed.is_file() else None
    for manifest in (committed, staged):
        if _is_named(manifest, named):
            return manifest
    raise ValueError(f"{run_dir.policy_set_dir} does not hold the policy set that {run_dir.CHECKPOINT} names")


def load_policy_set(
    run_dir: RunDirectory,
    n_policies: int | None = None,
    device: th.device | str = "cpu",
    iteration: int | None = None,
    record: bool = False,
) -> GPIPolicy:
    """
    Π of the run's checkpoint, or as it was at an earlier one: the first ``n_policies`` policies the run recorded,
    those that validation retired after ``iteration`` back in Π.

    :param n_policies: the checkpoint's ``n_policies`` (None: every saved policy)
    :param iteration: the checkpoint's ``iteration`` (None: retired policies stay retired)
    :param record: every recorded policy, the retired ones marked (what a run continues from); default: Π's
        members, what GPI acts over
    :raises ValueError: no policy set, or fewer policies than ``n_policies``
    """
    manifest = policy_set_manifest(run_dir)
    if manifest is None:
        raise ValueError(f"{run_dir} has no policy set yet")
    from sb3_sfgpi.gpi import GPIPolicy  # torch and SB3: only where Π is read, not where a run is looked at

    saved = GPIPolicy.load(manifest, device=device, retired=True)
    if n_policies is not None and n_policies > len(saved):
        raise ValueError(f"{run_dir.policy_set_dir} holds {len(saved)} policies, the checkpoint {n_policies}")
    policy_set = saved if n_policies is None else saved.subset(range(n_policies))
    if iteration is not None:
        policy_set = policy_set.as_of(iteration)
    return policy_set if record else policy_set.members()


def _named(run_dir: RunDirectory) -> str | None:
    """The digest of the Π the run's checkpoint names (None: no checkpoint, or one that names no set)."""
    return run_dir.read_checkpoint().get("policy_set") if run_dir.has_checkpoint() else None


def _is_named(manifest: Path, named: str | None) -> bool:
    """Whether ``manifest`` is there and is the one of digest ``named``."""
    return named is not None and manifest.is_file() and _digest(manifest) == named


def _digest(path: Path) -> str:
    """The SHA-256 digest of a file (a manifest: it names every file of its set)."""
    digest = hashlib.sha256()
    with path.open("rb") as file:
        for chunk in iter(lambda: file.read(2**20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _remove_unlisted_files(directory: Path) -> None:
    """Delete the policy files that neither the committed nor the staged manifest names (none if one is corrupt)."""
    listed = [_listed_files(directory / name) for name in (MANIFEST, STAGED_MANIFEST)]
    if any(names is None for names in listed):
        return
    keep = set().union(*listed)  # type: ignore[arg-type]
    for path in directory.glob("policy_*.pt"):
        if path.name not in keep:
            path.unlink()


def _listed_files(manifest: Path) -> set[str] | None:
    """The policy files a manifest names: none if it is missing, None if it is unreadable."""
    if not manifest.is_file():
        return set()
    try:
        entries = read_json(manifest, "policy-set manifest")["policies"]
        return {entry["file"] for entry in entries if isinstance(entry["file"], str)}
    except (KeyError, TypeError, ValueError):
        return None
