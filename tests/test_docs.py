"""The documentation: the site builds with `mkdocs build --strict`, the README is short and opens with the two
commands (the test command exactly as .ci/run runs it), and every `facerec3d` command shown uses commands and
options that exist."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import click
import pytest

from facerec3d.cli import main

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_the_site_builds_strictly(tmp_path):
    """Broken links, anchors, nav entries or docstrings the API page cannot render fail the build."""
    pytest.importorskip("mkdocs", reason="the docs extra is not installed: pip install -e '.[docs]'")
    pytest.importorskip("mkdocstrings", reason="the docs extra is not installed: pip install -e '.[docs]'")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
                        "-d", str(tmp_path / "site")], capture_output=True, text=True, cwd=ROOT,
                       env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert r.returncode == 0, r.stdout + r.stderr
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "Evaluate <code>method</code>" in api  # the docstrings are there, not just the headings


def _bash_blocks(text: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", text, re.S)


def test_the_readme_is_short_and_opens_with_the_two_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text) <= 15_000
    demo, tests = _bash_blocks(text)[:2]
    assert demo.strip() == "python3 -m venv .venv && . .venv/bin/activate && pip install -e . && facerec3d demo"
    ci = (ROOT / ".ci" / "run").read_text()
    assert tests.strip() in ci.splitlines()  # the README's test command is CI's, character for character
    assert '[ "$rc" -eq 5 ] && exit 0' in ci  # pytest's "no tests collected" is not a failure


def _commands(block: str):
    """The argument lists of the `facerec3d ...` command lines of a bash block (continuations joined)."""
    for line in block.replace("\\\n", " ").splitlines():
        for part in re.split(r"&&|\|", line):
            words = shlex.split(part, comments=True)
            if words and words[0] == "facerec3d":
                yield words[1:]


def _check(args: list[str], where: str) -> None:
    """Resolve the (sub)commands and check each --option belongs to the command it is given to."""
    command: click.Command = main
    names = ["facerec3d"]
    while isinstance(command, click.Group):
        options = {o for p in command.params for o in p.opts + p.secondary_opts}
        rest = [a for a in args if not a.startswith("-")]
        name = next((a for a in rest if a in command.commands), None)
        if name is None:
            if command is main:
                raise AssertionError(f"{where}: facerec3d {' '.join(args)}: no such command")
            break  # gallery STORE list: its subcommand follows the store
        before, args = args[:args.index(name)], args[args.index(name) + 1:]
        assert all(a in options or not a.startswith("--") for a in before), (where, names, before)
        command, names = command.commands[name], names + [name]
    options = {o for p in command.params for o in p.opts + p.secondary_opts} | {"--help"}
    for a in args:
        if a.startswith("--"):
            assert a.split("=")[0] in options, f"{where}: {' '.join(names)} has no option {a}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_command_shown_has_the_options_it_uses(page):
    text = page.read_text(encoding="utf-8")
    shown = [args for block in _bash_blocks(text) for args in _commands(block)]
    for args in shown:
        _check(args, page.name)
    if page.name in ("README.md", "depth-camera.md"):
        assert len(shown) >= 5


def test_the_check_finds_a_wrong_option():
    with pytest.raises(AssertionError, match="has no option --gallery-file"):
        _check(["identify", "p.png", "--gallery-file", "g.sqlite"], "example")
    with pytest.raises(AssertionError, match="no such command"):
        _check(["enrol", "p.png"], "example")


def test_the_built_in_thresholds_the_docs_give_are_the_codes():
    """docs/depth-camera.md said 3.0 and −1 mm² long after the defaults had become 4.0 and −1.8."""
    from facerec3d.gallery.service import DEFAULT_THRESHOLDS

    page = " ".join((ROOT / "docs" / "depth-camera.md").read_text(encoding="utf-8").split())
    assert f"{DEFAULT_THRESHOLDS['fusion']:g}.0 for the fusion" in page or \
        f"{DEFAULT_THRESHOLDS['fusion']:g} for the fusion" in page
    assert f"−{abs(DEFAULT_THRESHOLDS['icp']):g} mm² for ICP" in page
