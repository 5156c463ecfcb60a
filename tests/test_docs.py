"""The documentation site builds with warnings as errors (no broken link, no missing page or
anchor, no unresolved API reference), its generated pages hold every command and every public
name, and the README stays a front page."""

import os
import re
import subprocess
import sys
from pathlib import Path

import navapp
from navapp.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"


def subcommands() -> list[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return sorted(sub.choices)


def test_site_builds_strict_with_the_generated_references(tmp_path):
    site = tmp_path / "site"
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # the theme's notice about its successor
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                         cwd=ROOT, capture_output=True, text=True, env=env)
    assert run.returncode == 0, run.stderr[-4000:]
    commands = (site / "commands/index.html").read_text()
    for name in subcommands():
        assert f"navapp {name}" in commands, name
    assert "--local-modes" in commands and "--pose-sd" in commands  # the options, from the parser
    api = (site / "api/index.html").read_text()
    for name in navapp.__all__:
        target = navapp._EXPORTS[name]
        module, attr = target if isinstance(target, tuple) else (target, name)
        assert f'id="{module}.{attr}"' in api, name  # mkdocstrings rendered it
    assert "Parameters" in api and "Returns" in api  # numpydoc sections parsed
    front = (site / "index.html").read_text()
    assert "What to read next" in front and "opens the navigation viewer" in front  # the README is the home page


def test_readme_is_a_front_page():
    lines = README.read_text().splitlines()
    assert len(lines) <= 200
    block = README.read_text().split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert block[:2] == ['pip install -e . && navapp serve', 'pip install -e ".[test]" && python -m pytest -q']
    assert sum(line.startswith("![") for line in lines) == 1


def test_the_commands_page_lists_every_command():
    """The table of commands (docs/commands.md) names each of the parser's commands, and no other."""
    text = (ROOT / "docs/commands.md").read_text()
    listed = set(re.findall(r"^\| `navapp (\w[\w-]*)", text, flags=re.M))
    assert listed == set(subcommands())


def results_index() -> list[tuple[set[str], str]]:
    """docs/studies.md's table of every file in results/: per row, the file names (paths
    relative to results/, globs allowed) and the command cell."""
    text = (ROOT / "docs/studies.md").read_text().split("## Every file in results/", 1)[1]
    rows = [line for line in text.split("\n## ", 1)[0].splitlines() if line.startswith("| ") and "---" not in line]
    out = []
    for row in rows[1:]:  # the header first
        files, _, made_by = (cell.strip() for cell in row.strip("|").split(" | "))
        names = set(re.findall(r"\]\(results/([^)]+)\)", files))
        names |= set(re.findall(r"`([^`]+)`", re.sub(r"\[[^\]]*\]\([^)]*\)", "", files)))
        out.append((names, made_by))
    return out


def test_every_file_in_results_is_listed_with_the_command_that_makes_it():
    """results/ holds only what the docs list (docs/studies.md, "Every file in results/"), each
    beside a command the docs name: a navapp command, or a script that exists. A probe's output
    goes to notes/, not here."""
    from fnmatch import fnmatch

    on_disk = {str(p.relative_to(ROOT / "results")) for p in (ROOT / "results").rglob("*") if p.is_file()}
    listed: set[str] = set()
    commands = set(subcommands())
    for names, made_by in results_index():
        for name in names:
            matched = {f for f in on_disk if fnmatch(f, name)}
            assert matched, f"docs/studies.md lists results/{name}, which is not there"
            listed |= matched
        runs = re.findall(r"`((?:navapp|python) [^`]+)`", made_by)
        assert runs, f"no command for {sorted(names)}"
        for run in runs:
            words = run.split()
            if words[0] == "navapp":
                assert words[1] in commands, run
            elif words[1] != "-m":
                assert (ROOT / words[1]).is_file(), run
    assert sorted(on_disk - listed) == []


def test_mkdocs_serve_serves_the_front_page():
    """The README's ``mkdocs serve``: the site is built and served, the README its home page."""
    import socket
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "mkdocs", "serve", "--no-livereload", "--dev-addr",
                             f"127.0.0.1:{port}"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        page, deadline = "", time.monotonic() + 300  # a cold build on a loaded 2-core machine
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as response:
                    page = response.read().decode()
                break
            except OSError:
                time.sleep(0.5)
        assert proc.poll() is None, proc.stderr.read()[-3000:]
        assert "What to read next" in page and "opens the navigation viewer" in page
    finally:
        proc.terminate()
        proc.wait(timeout=60)


def test_the_docs_extra_is_installed_by_the_test_extra():
    """``pip install -e ".[docs]"`` (the README) installs nothing that CI's ``.[test]`` does not,
    so the suite's site build proves the docs extra too."""
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert extras["docs"] and set(extras["docs"]) <= set(extras["test"])
