"""The wheel a user installs: every module, the traffic networks, and a declared dependency for every package the
modules import at their top; MO-Gymnasium ids that need a package not installed say which."""

from __future__ import annotations

import ast
import importlib.util
import shutil
import subprocess
import sys
import zipfile
from email.parser import Parser
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest
from packaging.requirements import Requirement

from sb3_sfgpi.cli import main

ROOT = Path(__file__).resolve().parents[1]
#: Source folders and the packages they install as.
SOURCES = {"sb3_sfgpi": "sb3_sfgpi", "envs": "sfgpi_envs"}


#: What the wheel is built from: a copy of these, so that setuptools' ``build/`` never lands in the source tree (whose
#: stale files it would put in the next wheel).
PACKAGED = ("pyproject.toml", "README.md", "sb3_sfgpi", "envs")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("wheel")
    for name in PACKAGED:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(ROOT / name, source / name)
    command = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out)]
    subprocess.run([*command, str(source)], check=True, capture_output=True, timeout=300)
    (path,) = out.glob("sb3_sfgpi-*.whl")
    return zipfile.ZipFile(path)


def _modules() -> dict[str, Path]:
    """Every source module, by its path in the wheel."""
    return {
        f"{package}/{path.relative_to(ROOT / folder).as_posix()}": path
        for folder, package in SOURCES.items()
        for path in (ROOT / folder).rglob("*.py")
        if "__pycache__" not in path.parts
    }


def _top_level_imports(path: Path) -> set[str]:
    """The top-level packages a module imports when it is imported (not inside functions or TYPE_CHECKING)."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_the_wheel_holds_every_module_and_the_traffic_networks(wheel):
    names = set(wheel.namelist())
    missing = sorted(set(_modules()) - names)
    assert not missing, f"modules left out of the wheel (packages in pyproject.toml's [tool.setuptools]): {missing}"
    nets = ROOT / "envs" / "traffic" / "nets"
    assert {f"sfgpi_envs/traffic/nets/{p.name}" for p in nets.iterdir() if p.is_file()} <= names


def test_every_package_imported_at_a_modules_top_is_a_declared_dependency(wheel):
    (metadata,) = [name for name in wheel.namelist() if name.endswith(".dist-info/METADATA")]
    requirements = [Requirement(r) for r in Parser().parsestr(wheel.read(metadata).decode()).get_all("Requires-Dist")]
    core = {r.name.lower().replace("_", "-") for r in requirements if r.marker is None}
    distributions = packages_distributions()
    own = set(SOURCES.values())
    for module, path in _modules().items():
        for name in _top_level_imports(path) - own:
            if name in sys.stdlib_module_names or name == "__future__":
                continue
            assert importlib.util.find_spec(name) is not None, (module, name)
            declared = {d.lower().replace("_", "-") for d in distributions.get(name, [])} & core
            assert declared, f"{module} imports {name!r} at its top, but no dependency of the wheel provides it"


def test_an_id_whose_package_is_missing_names_it(capsys):
    if importlib.util.find_spec("highway_env") is not None:
        pytest.skip("highway-env is installed here")
    assert main(["train", "mo-highway-v0", "--iterations", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    expected = "mo-highway-v0 needs 'highway_env', which is not installed: pip install highway-env"
    assert err == [f"sb3-sfgpi train: error: {expected}"]
