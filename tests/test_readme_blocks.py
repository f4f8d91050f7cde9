"""Every README code block runs as written (issue 21): ``bench/readme.py`` runs each block in
order in one fresh folder, changing only what the ``readme-test`` comment above it says."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from readme import parse_blocks, script_for  # noqa: E402

README = (ROOT / "README.md").read_text()


def test_every_block_is_run_or_says_why_not():
    blocks = parse_blocks(README)
    assert len(blocks) == README.count("```bash")
    run = [b for b in blocks if not b.get("skip")]
    assert len(run) >= 3
    for block in blocks:
        for small in (False, True):
            for mirror in (None, Path("/mirror")):
                script, left_out = script_for(block, small, mirror)  # raises on a stale directive
                assert all("[" in line and line.endswith("]") for line in left_out)
    # Shrinking changes sizes only; the commands themselves are the README's.
    using = next(b for b in blocks if "vastray generate rm" in b.text)
    full, _ = script_for(using, False, Path("/mirror"))
    small, _ = script_for(using, True, Path("/mirror"))
    assert "--resolution 256 --grid 4x4x4" in full and "--resolution 64 --grid 2x2x2" in small
    assert "--from /mirror" in small
    _, without = script_for(using, True, None)
    assert any("vastray data fetch" in line for line in without)


def test_a_stale_directive_is_an_error(tmp_path):
    text = "<!-- readme-test\nshrink: --spp 99 => --spp 1\n-->\n```bash\nvastray render -o a.exr\n```\n"
    (block,) = parse_blocks(text)
    with pytest.raises(ValueError, match="--spp 99"):
        script_for(block, True, None)


@pytest.mark.timeout(2400)  # its own limit is 1,800 s
@pytest.mark.slow
def test_the_readme_runs_top_to_bottom(tmp_path):
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "readme.py"), "--small"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=1800)
    last = run.stdout.strip().splitlines()[-1]
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "failures=0 native_crashes=0" in last
