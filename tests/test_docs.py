"""The documents speak to users: no development-log words or machine paths in README.md,
docs/ (docs/development.md excepted) and the commands' help; every `softplot COMMAND` they name
exists; the README says what a newcomer needs; and the README tour runs, command by command."""

from __future__ import annotations

import importlib
import json
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
_ORDINAL = (r"(?:first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|"
            r"twelfth|\d+(?:st|nd|rd|th))")
_DATE = r"\d{4}-\d{2}-\d{2}"
#: words of a development log, not of a user's document
DEV_WORDS = re.compile(
    r"\bissues?[- ]\d|\bthe issue's\b|\bthe lead\b|DESIGN\.md|/work/|\bhelper's\b|\bthe helper\b"
    rf"|\b{_ORDINAL}(?: {_DATE})? session\b"  # "the fifth 2026-12-02 session"
    rf"|\b{_DATE} session\b"  # "in the 2026-12-02 session"
    # a development session, not a plotting session ("a file read for this session" is fine)
    r"|\b(?:until|since|before|after|earlier in|later in) this session\b"
    r"|\b(?:tried|dropped|measured|done|changed|added|adopted) in this session\b"
    r"|\bthis session's (?:changes|work|figures)\b|\b(?:earlier|previous) sessions\b"
    r"|\btried and dropped\b|\btried in (?:the|this|earlier)\b"
    rf"|\bthe {_ORDINAL} \d+\.\d"  # an ordinal standing for a session: "the sixth 1.8"
    r"|\bspeed round\b|\bround by round\b",
    re.IGNORECASE)
#: a commit hash in prose: 7-40 hex digits (a letter and a digit among them) in backticks or
#: parentheses, or after "commit" / "at"
COMMIT = re.compile(
    r"(?:[`(]|\bcommits? |\bat |\bsince |\buntil |\bbefore |; )"
    r"(?=[0-9a-f]{0,39}[a-f])(?=[0-9a-f]{0,39}\d)[0-9a-f]{7,40}\b(?![.\d])")
#: a section title carrying a date: history, not a reference
DATED_TITLE = re.compile(rf"^#+ .*\b{_DATE}\b")


def _dev_hits(name: str, text: str) -> list[str]:
    return [f"{name}:{i}: {line.strip()[:100]}"
            for i, line in enumerate(text.splitlines(), 1)
            if DEV_WORDS.search(line) or COMMIT.search(line) or DATED_TITLE.search(line)]


def _commands():
    out = {}
    for name, module, _ in COMMAND_TABLE:
        cmd = importlib.import_module(f"softplot.cli.{module}").command
        out[name] = cmd
    return out


@pytest.mark.parametrize("doc", USER_DOCS, ids=[p.name for p in USER_DOCS])
def test_no_development_log_in_user_docs(doc):
    hits = _dev_hits(doc.name, doc.read_text())
    assert not hits, "\n".join(hits)


@pytest.mark.parametrize("line, caught", [
    ("After the speed round of the second 2026-12-01 session (compiled kernel)", True),
    ("from the opening's estimate (20 until the fifth 2026-12-02 session, below)", True),
    ("Tried and dropped in this session (same harness):", True),
    ("Until this session each render was checked", True),
    ("Tried in the 2026-12-02 session, on the 32 busy renders", True),
    ("reach 1.05-1.2 x the bound (at fe5c3b8; the sixth 1.8): the gap", True),
    ("the full sweep at commit 37350ec (`SOFTPLOT_FULL=1`, 2.98 min)", True),
    ("a cross's affine, `b3cee5b`", True),
    ("### The joint scene estimate (2026-12-02)", True),
    ("Figures of the first 40 renders of the full sweep (seeds 0-39)", False),
    ("the session's scans; this session's journal", False),
    ("a file read for this session, and every file this session was made from", False),
    ("The issue-3 JSON document; the issue's formula", True),
    ("Tried and dropped in earlier sessions, because they were worse", True),
    ("after this session's fine-stage changes (the affine of each cross)", True),
    ("0.0044 px (1.5e-3 px), seed 1234567, RMS 0.0125", False),
    ("measured at `4fbb546` by the sweep", True),
])
def test_dev_words_catch_the_log(line, caught):
    """The checks catch the development log they are for, and leave ordinary text alone."""
    assert bool(_dev_hits("x", line)) is caught, line


def _user_visible_source_text(path: Path) -> list[tuple[int, str]]:
    """Docstrings and comments of a module (what --help, pydoc and a reader of the code see)."""
    import ast
    import io
    import tokenize
    src = path.read_text()
    out = []
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc and node.body:
                first = node.body[0].lineno
                out += [(first + k, line) for k, line in enumerate(doc.splitlines())]
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            out.append((tok.start[0], tok.string))
    return out


def test_no_development_log_in_source_and_tools():
    """Module, class and function docstrings and comments of softplot and of the benchmark tools
    (whose --help the docs send users to) name no machine path, no issue number and no
    development session."""
    hits = []
    for path in [*sorted((ROOT / "src" / "softplot").rglob("*.py")),
                 *sorted((ROOT / "tools").glob("*.py"))]:
        for lineno, line in _user_visible_source_text(path):
            if DEV_WORDS.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{lineno}: {line.strip()[:100]}")
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
    _demo_figures_match_accuracy_md(json.loads((tmp_path / "tour" / "demo.json").read_text()))


#: rows of docs/accuracy.md's demo table -> the keys of the demo's `demo.json`, in the order
#: the row gives its numbers
DEMO_ROWS = {
    "detection RMS": ["detection_rms_px"],
    "film correction": ["correction_rms_um", "correction_rms_reseau_um"],
    "relative orientation sigma0": ["relative_sigma0_um"],
    "absolute orientation sigma0": ["absolute_sigma0"],
    "check points after absolute orientation": ["check_rms_m"],
    "contour height error": ["contour_height_rms_m", "contour_height_max_m"],
    "height of the floating mark": ["contour_mark_height_rms_m"],
    "plan error of the recorded vertices": ["contour_plan_rms_m"],
}


def _demo_figures_match_accuracy_md(result: dict) -> None:
    """docs/accuracy.md gives the figures `softplot demo` prints today (each to the last digit
    it shows, one unit of that digit allowed for rounding)."""
    text = (ROOT / "docs" / "accuracy.md").read_text()
    section = text[text.index("## End to end: the demo chain"):]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 2:
            rows[cells[0]] = cells[1]
    bad = []
    for start, keys in DEMO_ROWS.items():
        label = next((k for k in rows if k.startswith(start)), None)
        if label is None:
            bad.append(f"no row '{start}'")
            continue
        want = []
        for k in keys:
            want += result[k] if isinstance(result[k], list) else [result[k]]
        shown = re.findall(r"\d+\.\d+", rows[label])[:len(want)]
        if len(shown) < len(want):
            bad.append(f"{start}: {rows[label]}")
            continue
        for s, w in zip(shown, want, strict=True):
            unit = 10.0 ** -len(s.split(".")[1])
            if abs(float(s) - w) > unit * 1.001:
                bad.append(f"{start}: docs {s}, demo {w:.6g}")
    assert not bad, bad


def test_named_tests_and_files_exist():
    """Every test, tool and repository file the user docs name (`tests/x.py::test_y`,
    `test_y`, `tools/z.py`) exists, so that "verified by" stays true."""
    defs = set()
    for path in (ROOT / "tests").rglob("*.py"):
        defs.update(re.findall(r"def (test_\w+)", path.read_text()))
    bad = []
    for doc in USER_DOCS:
        text = doc.read_text()
        for m in re.finditer(r"\b((?:tests|tools|src|data)/[\w./-]+\.(?:py|md|json|tif|toml|csv))"
                             r"(?:::(\w+))?", text):
            path, func = ROOT / m.group(1), m.group(2)
            if "*" in m.group(1):
                continue
            if not path.exists():
                bad.append(f"{doc.name}: {m.group(1)} does not exist")
            elif func and not re.search(rf"def {func}\b", path.read_text()):
                bad.append(f"{doc.name}: {m.group(1)} has no {func}")
        bad += [f"{doc.name}: no test {name}" for name in re.findall(r"`(?:::)?(test_\w+)`", text)
                if name not in defs]
    assert not bad, bad


def test_documented_tool_options_exist():
    """Every `tools/X.py --option` the user docs give runs: the tool's --help lists the option."""
    uses: dict[str, set[str]] = {}
    for doc in USER_DOCS:
        for m in re.finditer(r"(tools/\w+\.py)((?:[ \t]+(?:\\\n\s*)?[^\s`]+)*)", doc.read_text()):
            uses.setdefault(m.group(1), set()).update(
                re.findall(r"(?<![\w-])(--[a-z][\w-]*)", m.group(2)))
    assert len(uses) >= 5
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep
           + os.environ.get("PYTHONPATH", ""), "OPENBLAS_NUM_THREADS": "1"}
    bad = []
    for tool, options in sorted(uses.items()):
        r = subprocess.run([sys.executable, str(ROOT / tool), "--help"], env=env, cwd=ROOT,
                           capture_output=True, text=True, timeout=120)
        if r.returncode:
            bad.append(f"{tool} --help: exit {r.returncode}: {r.stderr[-300:]}")
        bad += [f"{tool}: no {o}" for o in sorted(options) if o not in r.stdout]
    assert not bad, bad


def _options(cmd: click.Command) -> set[str]:
    return {o for p in cmd.params for o in (*p.opts, *p.secondary_opts)}


def test_documented_options_exist():
    """Every `--option` of a `softplot COMMAND ...` line in the user docs is an option of that
    command (of its subcommand when one is named): no documented command fails on an option
    that was renamed."""
    cmds = _commands()
    bad, checked = [], 0
    for doc in USER_DOCS:
        text = doc.read_text()
        blocks = [b.replace("\\\n", " ") for b in re.findall(r"```[a-z]*\n(.*?)```", text, re.S)]
        spans = re.findall(r"`([^`\n]+)`", re.sub(r"```[a-z]*\n.*?```", "", text, flags=re.S))
        for line in "\n".join(blocks + spans).splitlines():
            m = re.search(r"(?:^|\s)softplot ([a-z][a-z_-]*)((?: [^|;&]*)?)", line)
            if not m or m.group(1) not in cmds:
                continue
            cmd, rest = cmds[m.group(1)], m.group(2).split()
            if isinstance(cmd, click.Group) and rest and rest[0] in cmd.commands:
                have = _options(cmd.commands[rest[0]]) | _options(cmd)
            elif isinstance(cmd, click.Group):  # the group's default form, or a placeholder
                have = _options(cmd).union(*(_options(c) for c in cmd.commands.values()))
            else:
                have = _options(cmd)
            for opt in re.findall(r"(?<![\w-])(--[a-z][\w-]*)", " ".join(rest)):
                checked += 1
                if opt not in have | {"--help"}:
                    bad.append(f"{doc.name}: softplot {m.group(1)} ... {opt}")
    assert checked > 50 and not bad, bad
