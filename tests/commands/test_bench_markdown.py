"""``thermal-edge bench ... --markdown PATH``: the page holds exactly what the bench printed, stamped
with the code (judged against git itself), the host and the date; a bad path is refused before the
bench runs; outside a checkout the stamp is the package's version."""
from __future__ import annotations

import datetime as dt
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from cli_in_process import te_here

from thermal_edge import __version__
from thermal_edge.commands import bench_page

REPO = Path(__file__).resolve().parents[2]


def test_the_page_is_what_the_bench_printed(tmp_path):
    page = tmp_path / "jacobian.md"
    before = dt.datetime.now(dt.UTC).replace(microsecond=0)
    r = te_here("bench", "jacobian", "--hours", "0.05", "--repeat", "1", "--markdown", page)
    after = dt.datetime.now(dt.UTC)
    assert r.returncode == 0, r.stderr
    assert f"wrote {page}" in r.stderr
    text = page.read_text(encoding="utf-8")
    assert text.startswith("# Benchmark: jacobian\n")
    body = re.search(r"^```text\n(.*)^```$", text, re.M | re.S)
    assert body is not None
    assert body.group(1) == r.stdout  # verbatim, every line the terminal saw
    assert "Jacobian of 39 nodes x 14 parameters" in body.group(1)
    code = re.search(r"^- \*\*Code:\*\* (.*)$", text, re.M).group(1)
    if shutil.which("git") and (REPO / ".git").exists():
        described = subprocess.run(["git", "-C", str(REPO), "describe", "--always"], capture_output=True,
                                   text=True, check=True).stdout.strip()
        changed = subprocess.run(["git", "-C", str(REPO), "diff", "--name-only", "HEAD", "--", "thermal_edge"],
                                 capture_output=True, text=True, check=True).stdout.strip()
        untracked = subprocess.run(["git", "-C", str(REPO), "ls-files", "--others", "--exclude-standard", "thermal_edge"],
                                   capture_output=True, text=True, check=True).stdout.strip()
        assert code == f"commit {described}" + ("-dirty" if changed or untracked else "")
    date = dt.datetime.strptime(re.search(r"^- \*\*Date:\*\* (.*) UTC$", text, re.M).group(1), "%Y-%m-%d %H:%M:%S")
    assert before <= date.replace(tzinfo=dt.UTC) <= after
    host = re.search(r"^- \*\*Host:\*\* (.*)$", text, re.M).group(1)
    import os
    import platform

    assert host.startswith(platform.node() + ":") and f"{os.cpu_count()} logical CPUs" in host


@pytest.mark.parametrize("name,why", [("page.txt", "must end in .md"), ("nodir/page.md", "no such directory")])
def test_a_bad_path_is_refused_before_the_bench_runs(tmp_path, name, why):
    r = te_here("bench", "jacobian", "--hours", "0.05", "--repeat", "1", "--markdown", tmp_path / name)
    assert r.returncode == 2
    assert why in r.stderr and r.stdout == ""  # refused before the bench printed anything
    assert not list(tmp_path.rglob("*.md"))


def test_outside_a_checkout_the_stamp_is_the_version(tmp_path):
    assert bench_page.code_version(tmp_path) == f"thermal-edge {__version__}"


def test_a_page_elsewhere_in_the_tree_does_not_make_the_code_dirty(tmp_path):
    """A checkout whose package is unchanged is clean though a docs page changed; a change in the
    package makes it dirty (a scratch repository laid out like this one)."""
    if not shutil.which("git"):
        pytest.skip("no git")
    repo = tmp_path / "repo"
    (repo / "thermal_edge").mkdir(parents=True)
    (repo / "docs").mkdir()
    (repo / "thermal_edge" / "x.py").write_text("x = 1\n")
    (repo / "docs" / "page.md").write_text("# Page\n")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    (repo / "docs" / "page.md").write_text("# Page, rewritten by a bench\n")
    assert bench_page.code_version(repo / "thermal_edge") == f"commit {head}"
    (repo / "thermal_edge" / "x.py").write_text("x = 2\n")
    assert bench_page.code_version(repo / "thermal_edge") == f"commit {head}-dirty"


def test_every_bench_takes_the_option():
    from thermal_edge.cli import build_parser

    parser = build_parser(["bench"])
    sub = next(a for a in parser._actions if a.dest == "command").choices["bench"]
    benches = next(a for a in sub._actions if a.dest == "bench").choices
    assert {"jacobian", "paper", "protection", "real", "fleet", "service"} <= set(benches)
    for name, p in benches.items():
        assert any("--markdown" in a.option_strings for a in p._actions), name


def test_the_committed_benchmark_pages_are_written_by_their_benches():
    """Every page of docs/benchmarks/ is a bench's own output: its title, the command that wrote it
    (a bench that exists) and the stamp; none is pasted by hand."""
    from thermal_edge.cli import build_parser

    parser = build_parser(["bench"])
    sub = next(a for a in parser._actions if a.dest == "command").choices["bench"]
    benches = next(a for a in sub._actions if a.dest == "bench").choices
    pages = sorted((REPO / "docs" / "benchmarks").glob("*.md"))
    assert pages
    for page in pages:
        text = page.read_text(encoding="utf-8")
        m = re.match(r"# Benchmark: (\w+)\n\nGenerated by `thermal-edge bench (\w+)[^`]*`; do not edit", text)
        assert m is not None and m.group(1) == m.group(2) and m.group(1) in benches, page.name
        for field in ("Code", "Host", "Date"):
            assert re.search(rf"^- \*\*{field}:\*\* \S", text, re.M), (page.name, field)
        assert re.search(r"^```text\n.+\n```$", text, re.M | re.S), page.name
