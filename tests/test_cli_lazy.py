"""`softplot --help` lists every command without importing any command module (quick start-up),
and the listed help is each command's own."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import click
from click.testing import CliRunner

import softplot.cli as cli_pkg
from softplot.cli import COMMAND_TABLE, cli


def test_table_help_is_each_commands_own():
    for name, module, short in COMMAND_TABLE:
        cmd = importlib.import_module(f"softplot.cli.{module}").command
        assert cmd.name == name, module
        assert short == cmd.get_short_help_str(limit=300), name


def test_every_command_module_is_listed():
    listed = {module for _, module, _ in COMMAND_TABLE}
    found = set()
    for info in pkgutil.iter_modules(cli_pkg.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"softplot.cli.{info.name}")
        if isinstance(getattr(mod, "command", None), click.Command):
            found.add(info.name)
    assert found == listed


def test_help_imports_no_command_module():
    code = (
        "import sys\n"
        "from softplot.cli import main\n"
        "try:\n"
        "    main(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = [m for m in ('numpy', 'scipy', 'cv2', 'matplotlib') if m in sys.modules]\n"
        "cmds = [m for m in sys.modules if m.startswith('softplot.cli.')]\n"
        "print('HEAVY', heavy, 'CMDS', cmds)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "HEAVY [] CMDS []" in out.stdout, out.stdout


def test_help_lists_commands_and_subcommand_runs():
    r = CliRunner().invoke(cli, ["--help"])
    assert r.exit_code == 0
    for name, _, _ in COMMAND_TABLE:
        assert f"  {name} " in r.output
    r = CliRunner().invoke(cli, ["cameras"])
    assert r.exit_code == 0 and "rollei-6006" in r.output
    r = CliRunner().invoke(cli, ["no-such-command"])
    assert r.exit_code == 2 and "No such command" in r.output


def test_python_dash_m_softplot():
    out = subprocess.run([sys.executable, "-m", "softplot", "--version"], capture_output=True,
                         text=True, check=True)
    assert "softplot" in out.stdout
