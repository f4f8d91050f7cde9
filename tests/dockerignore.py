"""What ``docker build`` sends as its build context, computed from ``.dockerignore`` by Docker's
rules (no container engine runs on our machines).

A port of ``github.com/moby/patternmatcher`` (``ignorefile.ReadAll``, ``Pattern.compile``,
``PatternMatcher.MatchesOrParentMatches``), the matcher the docker CLI and BuildKit use:
patterns are anchored at the context root (``*.store`` matches only at the top; ``**/``
matches any number of folders), a pattern matching a folder excludes everything in it, ``!``
lets back in, and the last pattern that matches a path decides.
"""

from __future__ import annotations

import os
import posixpath
import re
from dataclasses import dataclass
from pathlib import Path

_ESCAPE = set(".+()|{}$")


def read_patterns(text: str) -> list[str]:
    """The patterns of a ``.dockerignore`` text (``ignorefile.ReadAll``)."""
    patterns = []
    for n, line in enumerate(text.splitlines()):
        if n == 0:
            line = line.removeprefix("\ufeff")
        if line.startswith("#"):
            continue
        line = line.strip()
        if not line:
            continue
        invert = line.startswith("!")
        if invert:
            line = line[1:].strip()
        if line:
            line = posixpath.normpath(line)
            if len(line) > 1 and line.startswith("/"):
                line = line.lstrip("/") or "/"
        patterns.append("!" + line if invert else line)
    return patterns


@dataclass
class Pattern:
    """One compiled pattern (``patternmatcher.Pattern``)."""

    text: str
    exclusion: bool
    kind: str = "exact"
    regex: re.Pattern | None = None

    @classmethod
    def compile(cls, pattern: str) -> Pattern:
        exclusion = pattern.startswith("!")
        if exclusion:
            if pattern == "!":
                raise ValueError('illegal exclusion pattern: "!"')
            pattern = pattern[1:]
        regex, kind, pos, n = "^", "exact", 0, len(pattern)
        i = 0
        while pos < n:
            ch = pattern[pos]
            pos += 1
            if ch == "*":
                if pos < n and pattern[pos] == "*":
                    pos += 1
                    if pos < n and pattern[pos] == "/":
                        pos += 1
                    if pos == n:
                        if kind == "exact":
                            kind = "prefix"
                        else:
                            regex, kind = regex + ".*", "regexp"
                    else:
                        regex, kind = regex + "(.*/)?", "regexp"
                    if i == 0:
                        kind = "suffix"
                else:
                    regex, kind = regex + "[^/]*", "regexp"
            elif ch == "?":
                regex, kind = regex + "[^/]", "regexp"
            elif ch in _ESCAPE:
                regex += "\\" + ch
            elif ch == "\\":
                if pos < n:
                    regex, kind = regex + "\\" + pattern[pos], "regexp"
                    pos += 1
                else:
                    regex += "\\"
            elif ch in "[]":
                regex, kind = regex + ch, "regexp"
            else:
                regex += ch
            i += 1
        return cls(pattern, exclusion, kind, re.compile(regex + "$") if kind == "regexp" else None)

    def match(self, path: str) -> bool:
        if self.kind == "exact":
            return path == self.text
        if self.kind == "prefix":
            return path.startswith(self.text[:-2])
        if self.kind == "suffix":
            suffix = self.text[2:]
            return path.endswith(suffix) or (suffix[:1] == "/" and path == suffix[1:])
        return self.regex.search(path) is not None


class DockerIgnore:
    """``.dockerignore`` patterns; ``excluded(path)`` for a path relative to the context."""

    def __init__(self, patterns: list[str]):
        self.patterns = [Pattern.compile(p) for p in patterns]
        self.has_exclusions = any(p.exclusion for p in self.patterns)

    @classmethod
    def read(cls, context: Path) -> DockerIgnore:
        file = context / ".dockerignore"
        return cls(read_patterns(file.read_text()) if file.is_file() else [])

    def excluded(self, path: str) -> bool:
        matched = False
        parent = posixpath.dirname(path) or "."
        parents = parent.split("/")
        for pattern in self.patterns:
            if pattern.exclusion != matched:
                continue
            match = pattern.match(path)
            if not match and parent != ".":
                match = any(pattern.match("/".join(parents[:i + 1])) for i in range(len(parents)))
            if match:
                matched = not pattern.exclusion
        return matched


def build_context(context: Path) -> set[str]:
    """The files (``/``-separated, relative to ``context``) a build of ``context`` sends."""
    ignore = DockerIgnore.read(context)
    files = set()
    for top, dirs, names in os.walk(context):
        prefix = Path(top).relative_to(context).as_posix() + "/"
        prefix = "" if prefix == "./" else prefix
        if not ignore.has_exclusions:  # nothing can be let back in below an excluded folder
            dirs[:] = [d for d in dirs if not ignore.excluded(prefix + d)]
        files.update(prefix + n for n in names if not ignore.excluded(prefix + n))
    return files
