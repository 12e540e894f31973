"""A run directory as someone else might share it: a copy whose ``run.json`` was edited (tests of the trust model)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path


def edited(run: Path, tmp_path: Path, section: str, **values) -> Path:
    """A copy of ``run`` whose run.json sets ``values`` in ``section`` (env_kwargs or learner_kwargs)."""
    copy = tmp_path / "shared-with-me"
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(run, copy)
    config = json.loads((copy / "run.json").read_text())
    config[section].update(values)
    (copy / "run.json").write_text(json.dumps(config))
    return copy
