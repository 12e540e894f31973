"""The documentation: the Sphinx site builds without a warning, and every code block of README.md and docs/ runs.

Rules for the code blocks (fenced blocks of ``README.md`` and ``docs/**/*.md``):

* ``python`` blocks are executed, those of one file in order in one namespace, in a fresh temporary working
  directory (so ``runs/...`` paths of a page land there).
* ``bash``, ``console``, ``shell`` and ``sh`` blocks are read command by command (``\\`` continues a line, ``#``
  starts a comment, ``$`` prompts and ``&&`` chains are split):

  - ``sb3-sfgpi train four-room ...`` is run through the real CLI (``sb3_sfgpi.cli.main``) with a tiny budget
    appended (one iteration of 200 joint steps, no validation, 2 test weights), once per algorithm and file; the
    other ``train four-room`` commands of a file, ``train`` on other domains (SUMO episodes take minutes), ``--resume``,
    ``compare``, ``plot`` and ``sweep`` are parsed by the real CLI parser (a wrong option fails the test);
  - ``sb3-sfgpi evaluate RUN ...`` is run when an earlier block of the file trained ``RUN``, else parsed;
  - set-up and other commands are checked, not run: ``bash FILE`` and ``python FILE`` need the file in the
    repository, ``python -m MODULE`` the module, ``pip`` and other programs must be on ``PATH``.

* Commands written inline (`` `sb3-sfgpi ...` ``, `` `python -m benchmarks ...` ``, `` `python examples/...` `` in the
  text of README.md and docs/, outside code blocks) are parsed by the parser of the program they name: the CLI's,
  the benchmarks' or the example's (run up to its parser, which stops it), and so are the benchmark and example
  commands of shell blocks: a reader who copies one gets no argparse error.
* A block is skipped only when the line before its fence is ``<!-- no-test: REASON -->`` with a reason.
* Other languages (``text``, ``json``, ...) are not code and are not run.

The Sphinx build runs offline (no intersphinx), from scratch (``-E``) into a temporary directory, with warnings as
errors (``-W --keep-going``); every name of ``sb3_sfgpi.__all__`` and ``sfgpi_envs.__all__`` must be documented.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import importlib.util
import inspect
import io
import os
import re
import shlex
import shutil
import sys
import types
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.util import find_spec
from pathlib import Path
from unittest import mock

import pytest
from sfgpi_envs.traffic.sumo_backend import SumoNotFoundError

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
MARKDOWN = [ROOT / "README.md", *sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)]
SHELL = {"bash", "console", "shell", "sh"}
NO_TEST = re.compile(r"^<!--\s*no-test:\s*(\S.*?)\s*-->$")
FENCE = re.compile(r"^(`{3,}|~{3,})\s*([^\s`]*)")
TINY_BUDGET = ["--iterations", "1", "--steps-per-iteration", "200", "--no-progress"]
#: A command written inline in a page's text: the CLI, a benchmark or an example.
INLINE_COMMAND = re.compile(r"`((?:sb3-sfgpi|python -m benchmarks|python examples/)[^`]*)`")


@dataclass
class Block:
    path: Path
    line: int
    language: str
    code: str
    skip_reason: str | None = None


def code_blocks(path: Path) -> list[Block]:
    """The fenced code blocks of a Markdown file (MyST directives such as ``{toctree}`` are not code)."""
    lines = path.read_text(encoding="utf-8").split("\n")
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        match = FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        fence, language = match.group(1), match.group(2).lower()
        j = i + 1
        while j < len(lines) and not lines[j].startswith(fence):
            j += 1
        assert j < len(lines), f"{path}:{i + 1}: unclosed code fence"
        previous = lines[i - 1].strip() if i > 0 else ""
        marker = NO_TEST.match(previous)
        if previous.startswith("<!--") and "no-test" in previous:
            assert marker, f"{path}:{i}: a no-test marker needs a reason: <!-- no-test: REASON -->"
        if not language.startswith("{"):
            blocks.append(Block(path, i + 1, language, "\n".join(lines[i + 1 : j]), marker and marker.group(1)))
        i = j + 1
    return blocks


def shell_commands(code: str) -> list[list[str]]:
    """The commands of a shell block, each as its argument list."""
    commands: list[list[str]] = []
    logical = ""
    for raw in code.split("\n"):
        line = raw.rstrip()
        if line.startswith("$ "):
            line = line[2:]
        if line.endswith("\\"):
            logical += line[:-1] + " "
            continue
        logical += line
        words = shlex.split(logical, comments=True)
        logical = ""
        command: list[str] = []
        for word in [*words, "&&"]:
            if word in ("&&", ";", "||"):
                if command:
                    commands.append(command)
                command = []
            else:
                command.append(word)
    return commands


def inline_commands(path: Path) -> list[tuple[int, list[str]]]:
    """The commands written inline in the text of a Markdown file (outside code fences), with their line numbers."""
    commands, fence = [], None
    for number, line in enumerate(path.read_text(encoding="utf-8").split("\n"), start=1):
        match = FENCE.match(line)
        if match and (fence is None or line.startswith(fence)):
            fence = match.group(1) if fence is None else None
            continue
        if fence is None:
            commands += [(number, shlex.split(command)) for command in INLINE_COMMAND.findall(line)]
    return commands


class _Parsed(Exception):
    """Raised by the patched parser once a program's arguments parsed: the program goes no further."""


def parse_program(main: Callable[[], object], argv: list[str], name: str) -> None:
    """Run ``main`` (which parses ``argv`` with argparse) up to its parser: fail where the parser refuses ``argv``."""
    parse_args = argparse.ArgumentParser.parse_args

    def parse_and_stop(parser: argparse.ArgumentParser, args: object = None, namespace: object = None) -> None:
        parse_args(parser, args, namespace)
        raise _Parsed

    stderr = io.StringIO()
    with (
        mock.patch.object(argparse.ArgumentParser, "parse_args", parse_and_stop),
        mock.patch.object(sys, "argv", [name, *argv]),
        contextlib.redirect_stderr(stderr),
    ):
        try:
            main()
        except _Parsed:
            return
        except SystemExit as error:
            if error.code == 0:  # --help
                return
            raise AssertionError(f"{name} {' '.join(argv)}: its parser refuses it: {stderr.getvalue()}") from error
    raise AssertionError(f"{name} {' '.join(argv)}: it parsed no arguments")


def parse_python(args: list[str]) -> None:
    """Parse ``python -m benchmarks ...`` or ``python examples/X.py ...`` with the program's own parser."""
    if args[:2] == ["-m", "benchmarks"]:
        from benchmarks.__main__ import main as benchmarks_main

        parse_program(lambda: benchmarks_main(args[2:]), args[2:], "python -m benchmarks")
    elif args[0].startswith("examples/") and args[0].endswith(".py"):
        spec = importlib.util.spec_from_file_location(f"_docs_{Path(args[0]).stem}", ROOT / args[0])
        assert spec and spec.loader, f"python {args[0]}: no such file in the repository"
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        entry = getattr(module, "parse_args", None) or module.main
        takes_argv = bool(inspect.signature(entry).parameters)  # parse_args(argv) or parse_args() reading sys.argv
        parse_program(functools.partial(entry, args[1:]) if takes_argv else entry, args[1:], f"python {args[0]}")


_TRAINED: dict[str, Path] = {}  # algorithm -> a tiny four-room run this process trained (tmp dirs live on)


@dataclass
class CliState:
    """What the shell blocks of one file trained (in the file's temporary directory)."""

    trained_algos: set[str] = field(default_factory=set)
    runs: set[str] = field(default_factory=set)


def parse_cli(argv: list[str]):
    from sb3_sfgpi.cli import parse_args

    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr):
            return parse_args(argv)
    except SystemExit as error:
        raise AssertionError(f"sb3-sfgpi {' '.join(argv)}: the CLI parser refuses it: {stderr.getvalue()}") from error


def quiet_preset_options(algo: str) -> list[str]:
    """Preset settings that make a tiny run fast: no validation, 2 test weights (through ``--set`` where it exists)."""
    settings = {"n_test_weights": "2"} if algo == "fixed" else {"validation_weights": "0", "n_test_weights": "2"}
    for options in (
        [word for key, value in settings.items() for word in ("--set", f"{key}={value}")],
        [word for key, value in settings.items() for word in (f"--{key.replace('_', '-')}", value)],
    ):
        try:
            parse_cli(["train", "four-room", "--algo", algo, *options])
            return options
        except AssertionError:
            continue
    return []


def run_cli(argv: list[str]) -> None:
    from sb3_sfgpi.cli import main

    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(argv)
    assert code == 0, f"sb3-sfgpi {' '.join(argv)} exited with {code}: {stderr.getvalue()[-2000:]}"


def check_sb3_sfgpi(argv: list[str], state: CliState) -> None:
    args = parse_cli(argv)
    if args.command == "train" and args.domain == "four-room" and not args.resume:
        if args.out and args.algo in _TRAINED:  # this process ran it already: the same tiny run, copied
            if not Path(args.out).exists():
                shutil.copytree(_TRAINED[args.algo], args.out)
            state.runs.add(os.path.normpath(args.out))
            return
        if args.algo in state.trained_algos:
            return  # parsed; one tiny run per algorithm and file is enough
        state.trained_algos.add(args.algo)
        before = set(Path.cwd().glob("**/run.json"))
        run_cli([*argv, *TINY_BUDGET, *quiet_preset_options(args.algo)])
        (run_file,) = set(Path.cwd().glob("**/run.json")) - before  # the run directory, wherever the CLI put it
        _TRAINED[args.algo] = run_file.parent
        state.runs.add(os.path.normpath(run_file.parent.relative_to(Path.cwd())))
    elif args.command == "evaluate" and os.path.normpath(args.run_dir) in state.runs:
        run_cli(argv)


def check_command(argv: list[str], state: CliState) -> None:
    program, args = argv[0], argv[1:]
    if program == "sb3-sfgpi":
        check_sb3_sfgpi(args, state)
    elif program == "bash":
        assert (ROOT / args[0]).is_file(), f"bash {args[0]}: no such file in the repository"
    elif program == "python":
        if args[0] == "-m":
            module = args[1]
            found = importlib.util.find_spec(module) or (ROOT / module).is_dir()
            assert found, f"python -m {module}: no such module"
        else:
            assert (ROOT / args[0]).is_file(), f"python {args[0]}: no such file in the repository"
        parse_python(args)
    else:
        assert shutil.which(program), f"{program}: not on PATH"


#: Packages of the extras (``pip install -e ".[dev]"``) that a page's example may need; a machine without one (a GPU
#: box's offline install) skips that page's block, naming the package, instead of failing it.
OPTIONAL_PACKAGES = ("momaland", "ray", "sumo_rl", "morl_baselines")


def run_python(code: str, namespace: dict, where: str) -> None:
    missing = [name for name in OPTIONAL_PACKAGES if re.search(rf"\b{name}\b", code) and not find_spec(name)]
    if missing:
        pytest.skip(f"{where}: needs {', '.join(missing)}, not installed here")
    try:
        exec(compile(code, where, "exec"), namespace)
    except SumoNotFoundError as error:  # a machine without SUMO (a GPU box's offline install): the page cannot run
        pytest.skip(f"{where}: {error}")
    except Exception as error:  # noqa: BLE001 - report which block broke
        raise AssertionError(f"{where}: {type(error).__name__}: {error}") from error


@pytest.fixture
def in_tmp_dir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(ROOT))
    return tmp_path


@pytest.mark.parametrize("path", MARKDOWN, ids=[str(p.relative_to(ROOT)) for p in MARKDOWN])
def test_code_blocks_run(path: Path, in_tmp_dir, monkeypatch) -> None:
    import torch

    torch.set_num_threads(1)
    page = types.ModuleType("__docs__")  # a module, as a user's script is: what it defines pickles by reference
    monkeypatch.setitem(sys.modules, page.__name__, page)
    namespace: dict = page.__dict__
    state = CliState()
    with contextlib.redirect_stdout(io.StringIO()):
        for block in code_blocks(path):
            where = f"{path.relative_to(ROOT)}:{block.line}"
            if block.skip_reason:
                continue
            if block.language == "python":
                run_python(block.code, namespace, where)
            elif block.language in SHELL:
                for argv in shell_commands(block.code):
                    try:
                        check_command(argv, state)
                    except AssertionError as error:
                        raise AssertionError(f"{where}: {error}") from error


@pytest.mark.parametrize("path", MARKDOWN, ids=[str(p.relative_to(ROOT)) for p in MARKDOWN])
def test_inline_commands_parse(path: Path, monkeypatch) -> None:
    from sb3_sfgpi.cli import main

    monkeypatch.syspath_prepend(str(ROOT))
    refused = []
    for line, argv in inline_commands(path):
        if argv[0] == "sb3-sfgpi" and len(argv) <= 2:
            continue  # the program or one of its commands named, as `sb3-sfgpi compare` is
        try:
            if argv[0] == "sb3-sfgpi":
                parse_program(functools.partial(main, argv[1:]), argv[1:], "sb3-sfgpi")
            else:
                parse_python(argv[1:])
        except AssertionError as error:
            refused.append(f"{path.relative_to(ROOT)}:{line}: {str(error).splitlines()[0]}")
    assert not refused, "\n".join(refused)


def test_the_inline_checks_can_fail(tmp_path, monkeypatch) -> None:
    """An inline command with a removed option, or a benchmark's unknown option, is caught."""
    monkeypatch.syspath_prepend(str(ROOT))
    page = tmp_path / "page.md"
    page.write_text("Run `sb3-sfgpi train four-room --sharing shared` or\n```bash\n`sb3-sfgpi x`\n```\n", "utf-8")
    assert inline_commands(page) == [(1, ["sb3-sfgpi", "train", "four-room", "--sharing", "shared"])]
    with pytest.raises(AssertionError, match="parser refuses"):
        parse_cli(["train", "four-room", "--sharing", "shared"])
    with pytest.raises(AssertionError, match="parser refuses"):
        parse_python(["-m", "benchmarks", "known-fronts", "--no-such-option"])
    with pytest.raises(AssertionError, match="parser refuses"):
        parse_python(["examples/four_room.py", "--no-such-option"])
    parse_python(["-m", "benchmarks", "known-fronts", "--seeds", "0"])  # a good one parses


def test_the_block_checks_can_fail(tmp_path, monkeypatch) -> None:
    """A broken block, an unknown option and a missing script are caught (the checks above are not vacuous)."""
    monkeypatch.chdir(tmp_path)
    page = tmp_path / "page.md"
    page.write_text("text\n\n```python\nraise RuntimeError('broken')\n```\n", encoding="utf-8")
    (block,) = code_blocks(page)
    with pytest.raises(AssertionError, match="broken"):
        run_python(block.code, {}, "page.md")
    with pytest.raises(AssertionError, match="parser refuses"):
        check_command(["sb3-sfgpi", "train", "four-room", "--no-such-option"], CliState())
    with pytest.raises(AssertionError, match="no such file"):
        check_command(["python", "examples/no_such_example.py"], CliState())
    page.write_text("<!-- no-test: -->\n```bash\nls\n```\n", encoding="utf-8")
    with pytest.raises(AssertionError, match="needs a reason"):
        code_blocks(page)
    assert shell_commands("a x \\\n  --y 1  # c\n$ b && c") == [["a", "x", "--y", "1"], ["b"], ["c"]]


def test_a_block_skips_only_for_an_extra_that_is_missing(monkeypatch) -> None:
    """A block naming an extra's package that is not installed skips; "array" is not Ray, and a present one runs."""
    monkeypatch.setattr(sys.modules[__name__], "find_spec", lambda name: None if name in ("momaland", "ray") else True)
    with pytest.raises(pytest.skip.Exception, match="needs momaland"):
        run_python("import momaland", {}, "page.md")
    with pytest.raises(AssertionError, match="NameError"):
        run_python("x = array", {}, "page.md")
    with pytest.raises(AssertionError, match="NameError"):
        run_python("sumo_rl.nets", {}, "page.md")


def sphinx_build(source: Path, out: Path) -> tuple[int, str]:
    """Build ``source`` into ``out`` in this process (the package is imported once): exit code and warnings."""
    build_main = pytest.importorskip("sphinx.cmd.build", reason="Sphinx is in the dev extra").build_main

    warnings = out.parent / f"{out.name}-warnings.txt"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as stderr:
        code = build_main(["-b", "html", "-E", "-W", "--keep-going", "-q", "-w", str(warnings), str(source), str(out)])
    text = warnings.read_text(encoding="utf-8") if warnings.exists() else ""
    return code, text + stderr.getvalue()


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::PendingDeprecationWarning")  # Sphinx extensions
def test_sphinx_build_has_no_warning(tmp_path) -> None:
    code, warnings = sphinx_build(DOCS, tmp_path / "html")
    assert code == 0 and "WARNING" not in warnings, warnings[-5000:]
    html = "\n".join(p.read_text(encoding="utf-8") for p in (tmp_path / "html" / "api").glob("*.html"))
    for package in ("sb3_sfgpi", "sfgpi_envs"):
        module = importlib.import_module(package)
        for name in module.__all__:
            if name.startswith("_"):
                continue
            obj = getattr(module, name)
            anchor = f'id="{obj.__module__}.{obj.__qualname__}"'
            assert anchor in html, f"{package}.{name} is not in the API reference ({anchor})"


@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::PendingDeprecationWarning")  # Sphinx extensions
def test_sphinx_build_fails_on_a_warning(tmp_path) -> None:
    """The build's warnings are errors: a page with a broken cross-reference fails it."""
    source = tmp_path / "src"
    source.mkdir()
    (source / "conf.py").write_text('extensions = ["myst_parser"]\n', encoding="utf-8")
    (source / "index.md").write_text("# Page\n\n[a link](missing.md)\n", encoding="utf-8")
    code, warnings = sphinx_build(source, tmp_path / "html")
    assert code != 0 and "WARNING" in warnings
