"""What a new user hit (issue 42, part 4), the small things: help text, sizes and their units,
output folders, the frames plot's legend, a fixed colour range. The CLI in subprocesses where
the point is what a user sees."""

from __future__ import annotations

import argparse
import subprocess
import sys

from vastray.cli import build_parser

VASTRAY = [sys.executable, "-m", "vastray.cli"]


def _cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([*VASTRAY, *args], capture_output=True, text=True, timeout=timeout)


def _parsers(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """Every (command words, parser) of the command line, nested sub-commands included."""
    yield prefix, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, (*prefix, name))


def test_no_help_shows_an_argparse_escape():
    # `vastray render --help` showed "95%%": an argument group's description is not
    # %-formatted, so its escape reached the user
    commands = list(_parsers(build_parser()))
    assert len(commands) > 10
    for words, parser in commands:
        assert "%%" not in parser.format_help(), f"vastray {' '.join(words)} --help shows %%"
    for words in (["render"], ["launch"], ["node"], []):
        run = _cli(*words, "--help", timeout=120)
        assert run.returncode == 0, run.stderr
        assert "%%" not in run.stdout, f"vastray {' '.join(words)} --help shows %%"


def test_the_top_help_names_every_output_of_render():
    # `vastray --help` said render writes "to OpenEXR" only
    run = _cli("--help", timeout=120)
    assert run.returncode == 0, run.stderr
    text = " ".join(run.stdout.split())
    line = text[text.index("render render"):text.index("launch render")]
    assert "OpenEXR" not in line
    for word in (".exr", ".png", "PNG preview", "JSON report"):
        assert word in line, line
