"""bench/README.md is one section per bench script, and every link into it lands on a section."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH_README = (ROOT / "bench" / "README.md").read_text()
HELPERS = {"bench_scenes.py", "bytecode.py", "fault_attacker.py", "fault_node.py",
           "fault_proxy.py", "hogs.py", "numba_env.py", "pair_noise.py", "replay_scaling.py"}


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but - and _ dropped, spaces to -."""
    text = heading.strip().lower().replace("`", "")
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors() -> set[str]:
    return {_slug(h) for h in re.findall(r"^#{1,6} (.+)$", BENCH_README, flags=re.M)}


def test_every_bench_script_has_its_own_section():
    sections = set(re.findall(r"^## `(\w+\.py)`$", BENCH_README, flags=re.M))
    scripts = {p.name for p in (ROOT / "bench").glob("*.py")} - HELPERS
    assert scripts <= sections, sorted(scripts - sections)
    assert sections <= scripts, sorted(sections - scripts)
    assert "Earlier measurements: `git log -p bench/README.md`" in BENCH_README.split("\n## ")[0]


def test_links_into_bench_readme_land_on_a_section():
    anchors = _anchors()
    links = re.findall(r"\]\(#([^)]+)\)", BENCH_README)
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        links += re.findall(r"bench/README\.md#([\w\-]+)", doc.read_text())
    assert links
    assert not [a for a in links if a not in anchors]
