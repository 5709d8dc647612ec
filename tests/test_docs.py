"""The documents speak to users: no development-log words or machine paths in README.md,
docs/ (docs/development.md excepted) and the commands' help; every `softplot COMMAND` they name
exists; the README says what a newcomer needs; and the README tour runs, command by command."""

from __future__ import annotations

import importlib
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from softplot.cli import COMMAND_TABLE, cli

ROOT = Path(__file__).resolve().parents[1]
USER_DOCS = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").glob("*.md")
                                         if p.name != "development.md")]
DEV_WORDS = re.compile(
    r"\bissues? \d|\bthe lead\b|\b(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|"
    r"tenth|\d+(st|nd|rd|th)) session\b|DESIGN\.md|/work/|\bhelper's\b|\bthe helper\b",
    re.IGNORECASE)


def _commands():
    out = {}
    for name, module, _ in COMMAND_TABLE:
        cmd = importlib.import_module(f"softplot.cli.{module}").command
        out[name] = cmd
    return out


@pytest.mark.parametrize("doc", USER_DOCS, ids=[p.name for p in USER_DOCS])
def test_no_development_log_in_user_docs(doc):
    hits = [f"{doc.name}:{i}: {line.strip()[:80]}"
            for i, line in enumerate(doc.read_text().splitlines(), 1) if DEV_WORDS.search(line)]
    assert not hits, "\n".join(hits)


def test_no_development_log_in_help():
    def walk(cmd, path):
        yield path
        if isinstance(cmd, click.Group):
            for n, sub in cmd.commands.items():
                yield from walk(sub, [*path, n])

    hits = []
    for name, cmd in _commands().items():
        for path in walk(cmd, [name]):
            text = CliRunner().invoke(cli, [*path, "--help"]).output
            hits += [f"softplot {' '.join(path)}: {m.group(0)}" for m in DEV_WORDS.finditer(text)]
    assert not hits, hits


def test_documented_commands_exist():
    cmds = _commands()
    missing = []
    for doc in USER_DOCS:
        text = doc.read_text()
        blocks = re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
        spans = re.findall(r"`([^`\n]+)`", re.sub(r"```[a-z]*\n.*?```", "", text, flags=re.S))
        code = blocks + spans
        for m in re.finditer(r"(?:^|\s)softplot ([a-z][a-z_-]*)(?: ([a-z][a-z-]*))?",
                             "\n".join(code), re.M):
            name, sub = m.group(1), m.group(2)
            if name not in cmds:
                missing.append(f"{doc.name}: softplot {name}")
            elif (sub and isinstance(cmds[name], click.Group) and sub not in cmds[name].commands
                  and name != "correct"):  # correct's default form takes a scan, not a command
                missing.append(f"{doc.name}: softplot {name} {sub}")
    assert not missing, missing


def test_readme_tells_a_newcomer():
    text = (ROOT / "README.md").read_text()
    for need in ("Python 3.11", ".venv/bin/softplot", "source .venv/bin/activate",
                 "Scanning your film", "--rotate", "dpi", "16 bit", "make demo", "make test"):
        assert need in text, need


def _tour_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    tour = text[text.index("## Five-minute tour"):]
    tour = tour[:tour.index("\n## ", 5)]
    cmds = []
    for block in re.findall(r"```sh\n(.*?)```", tour, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                cmds.append(line)
    return cmds


def test_readme_tour_runs(tmp_path):
    """Every command of the README tour, in order, from a copy of the repository's data; the
    viewer (a server that runs until Ctrl-C) is started with --help only."""
    shutil.copytree(ROOT / "data", tmp_path / "data")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep
           + os.environ.get("PYTHONPATH", ""), "OPENBLAS_NUM_THREADS": "1"}
    cmds = _tour_commands()
    assert cmds[0].startswith("softplot demo") and len(cmds) >= 10
    py = shlex.quote(sys.executable)
    for line in cmds:
        argv = shlex.split(line)
        if argv[0] == "softplot" and argv[1] == "view":
            line = f"softplot view {shlex.quote(argv[2])} --help"
        elif argv[0] == "softplot" and argv[1] == "demo" and "--quiet" not in argv:
            line += " --quiet"
        line = re.sub(r"^softplot ", f"{py} -m softplot ", line)
        line = re.sub(r"^python ", f"{py} ", line)
        # as a user's shell runs it: globs expanded, quotes removed
        r = subprocess.run(["bash", "-c", line], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, f"{line}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
