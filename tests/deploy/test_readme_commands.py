"""Every command the README and the manual show copy-pastes: each ``thermal-edge`` line parses with
the real command-line parser, every option of the other Python entry points is in their ``--help``,
every repository file a command names exists, every ``make`` target is in the Makefile, and the
quick commands of the README's "Commands" section run in a scratch directory and print what the
manual says.

Commands that need root, a running systemd, Docker or CAN hardware (sudo, systemctl, docker,
candump on can0, …) are not run here: their own tests run them where they can (tests/deploy,
tests/vm); this file checks that the files and options they name exist.
"""
from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import deploylib as dl
import pytest

from thermal_edge.cli import build_parser

README = dl.REPO / "README.md"
#: the files whose sh blocks are checked: the README and every page of the manual
PAGES = [README, *sorted(p for p in (dl.REPO / "docs").rglob("*.md") if "_generated" not in p.parts)]
#: what may precede a command on a line (a prompt's privilege, the venv's or the install's bin/)
PREFIXES = ("sudo",)
#: programs of the README that are not this project's and that the suite does not run (see the docstring)
NOT_RUN = {"sudo", "systemctl", "journalctl", "curl", "docker", "ip", "candump", "xdg-open", "sudoedit", "install",
           "promtool", "sed", "grep", "mkdir", "python3", "pip", "log2asc", "cd", "git", "dask", "modprobe", "tee"}
#: repository paths a command may name, recognised by their first component
REPO_DIRS = ("config/", "deploy/", "dbc/", "docs/", "tests/")


def shell_blocks(pages: list[Path] | None = None) -> list[tuple[str, str]]:
    """The ``sh`` blocks of ``pages`` (default: :data:`PAGES`): (file and line of the block, text)."""
    out = []
    for page in pages or PAGES:
        lines = page.read_text(encoding="utf-8").splitlines()
        i = 0
        while i < len(lines):
            if lines[i].strip() in ("```sh", "```bash"):
                j = i + 1
                while not lines[j].startswith("```"):
                    j += 1
                out.append((f"{page.relative_to(dl.REPO)}:{i + 1}", "\n".join(lines[i + 1:j])))
                i = j
            i += 1
    return out


def commands() -> list[tuple[str, list[str]]]:
    """Every simple command of the sh blocks as (where, argv): continuation lines joined, comments
    dropped, pipelines and ``&&`` lists split."""
    out = []
    for where, text in shell_blocks():
        for k, line in enumerate(text.replace("\\\n", " ").splitlines()):
            lex = shlex.shlex(line, posix=True, punctuation_chars="|&;<>")
            lex.whitespace_split = True
            lex.commenters = "#"
            argv: list[str] = []
            redirect = False
            for tok in [*lex, ";"]:
                if redirect:  # the file of a redirection is not an argument
                    redirect = False
                elif tok in (">", ">>", "<", ">&", "&>"):
                    redirect = True
                    if argv and argv[-1].isdigit():  # 2> file: the descriptor is not an argument either
                        argv.pop()
                elif tok in ("|", "&&", ";", "||"):
                    if argv:
                        out.append((f"{where} (block), line {k + 1}", argv))
                    argv = []
                else:
                    argv.append(tok)
    return out


def program(argv: list[str]) -> tuple[str, list[str]]:
    """The program's base name and its arguments, privilege prefixes dropped."""
    while argv and argv[0] in PREFIXES and len(argv) > 1:
        argv = argv[1:]
    return Path(argv[0]).name, argv[1:]


def test_the_readme_has_the_commands_this_file_checks():
    names = {program(a)[0] for _, a in commands()}
    # a count made another way: the README's lines that start with the venv's thermal-edge
    text = README.read_text(encoding="utf-8")
    assert len(re.findall(r"^(?:\.venv/bin/|/opt/thermal-edge/bin/)?thermal-edge ", text, re.M)) >= 10
    assert {"thermal-edge", "make", "python", "systemctl", "docker"} <= names


@pytest.mark.parametrize("where,argv", [c for c in commands() if program(c[1])[0] == "thermal-edge"],
                         ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else v)
def test_every_thermal_edge_command_parses(where, argv, tmp_path, monkeypatch):
    _, args = program(argv)
    # as the page runs it: from a checkout, after the page's own `mkdir -p` (an --out checks its directory)
    for entry in dl.REPO.iterdir():
        if not entry.name.startswith(".") and entry.name != "out":
            (tmp_path / entry.name).symlink_to(entry)
    for _, made in commands():
        if program(made)[0] == "mkdir":
            for d in (a for a in program(made)[1] if not a.startswith("-")):
                (tmp_path / d).mkdir(parents=True, exist_ok=True)
    monkeypatch.chdir(tmp_path)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            ns = build_parser(args).parse_args(args)
        except SystemExit as exc:
            if exc.code == 0 and ("--help" in args or "-h" in args):  # the help, printed: it parsed
                return
            pytest.fail(f"{where}: `{shlex.join(argv)}` does not parse (exit {exc.code}): {err.getvalue().strip()}")
    assert callable(ns.func)


def _python_module(args: list[str]) -> tuple[str, list[str]] | None:
    if len(args) >= 2 and args[0] == "-m":
        return args[1], args[2:]
    return None


@pytest.mark.parametrize("where,argv", [c for c in commands() if program(c[1])[0] == "python"
                                        and (_python_module(program(c[1])[1]) or ("", []))[0].startswith("thermal_edge")],
                         ids=lambda v: " ".join(v)[:60] if isinstance(v, list) else v)
def test_every_option_of_a_python_entry_point_is_in_its_help(where, argv):
    module, args = _python_module(program(argv)[1])
    helptext = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=60,
                              cwd=dl.REPO, env={**os.environ, "COLUMNS": "200"})
    assert helptext.returncode == 0, helptext.stderr
    for opt in (a.split("=")[0] for a in args if a.startswith("--")):
        assert re.search(rf"(^|[\s,\[]){re.escape(opt)}\b", helptext.stdout), f"{where}: {module} has no option {opt}"


def test_every_repository_file_a_command_names_exists():
    missing = []
    for where, argv in commands():
        for a in argv:
            for part in re.split(r"[=:,]", a):
                if part.startswith(REPO_DIRS) and not (dl.REPO / part).exists():
                    missing.append(f"{where}: {part}")
    assert missing == []


def test_every_make_target_exists():
    makefile = (dl.REPO / "Makefile").read_text(encoding="utf-8")
    targets = set(re.findall(r"^([\w-]+):", makefile, re.M))
    used = {program(a)[1][0] for _, a in commands() if program(a)[0] == "make"}
    assert used and used <= targets


def test_the_other_programs_are_the_ones_the_docstring_names():
    # a new program in the README is either this project's (checked above) or named in NOT_RUN
    ours = {"thermal-edge", "python", "make", "xdg-open"}
    others = {program(a)[0] for _, a in commands()} - ours
    assert others <= NOT_RUN, others - NOT_RUN


def test_the_commands_section_runs_in_a_scratch_directory(tmp_path):
    """The quick lines of the README's "Commands" block, copied as they are, in a directory that has
    only the repository's config/ and .venv beside it; what they print is what the manual shows."""
    block = next(t for n, t in shell_blocks([README]) if "thermal-edge simulate" in t and "calibrate" in t)
    lines = [ln for ln in block.splitlines() if ln.startswith(("mkdir", ".venv/bin/thermal-edge simulate"))]
    assert len(lines) == 2, lines  # mkdir -p out, then the simulation
    (tmp_path / "config").symlink_to(dl.REPO / "config")
    (tmp_path / ".venv").mkdir()
    (tmp_path / ".venv" / "bin").symlink_to(Path(sys.executable).parent)
    script = "set -e\n" + "\n".join(lines) + "\n"
    r = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    run = tmp_path / "out" / "run.csv"
    assert run.exists()
    # the manual's summary line of this very file: 10801 samples every 1 s (3.00 h)
    commands_page = (dl.REPO / "docs" / "guide" / "commands.md").read_text(encoding="utf-8")
    shown = re.search(r"^out/run\.csv: (\d+) samples every 1 s \(3\.00 h\)", commands_page, re.M)
    assert shown is not None
    body = [ln for ln in run.open(encoding="utf-8") if not ln.startswith("#")][1:]  # comment lines, then the header
    rows = len(body)
    assert float(body[1].split(",")[0]) - float(body[0].split(",")[0]) == 1.0
    assert float(body[-1].split(",")[0]) - float(body[0].split(",")[0]) == 3 * 3600
    assert rows == int(shown.group(1))
    assert f"wrote out/run.csv: {rows} samples" in r.stdout
    # nothing is written beside the scratch directory's out/
    assert sorted(p.name for p in tmp_path.iterdir()) == [".venv", "config", "out"]
