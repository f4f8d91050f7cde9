"""Every progress bar (``scene.progressbar.Bar`` and the render's ``RenderBar``) survives a
Ctrl-C that lands while it is being made: the interrupt propagates, and the half-made bar is
collected without a traceback (one was printed after an animation interrupted at its first
frame: tqdm sets ``disable`` before ``pos``)."""

from __future__ import annotations

import gc
import io
import sys

import pytest
from tqdm import tqdm

from vastray.render.progress import RenderBar
from vastray.scene.progressbar import Bar


@pytest.mark.parametrize("make", [
    lambda out: Bar(total=10, file=out),
    lambda out: RenderBar(total=10, compiled=True, file=out)])
def test_a_bar_interrupted_while_made_is_collected_without_a_traceback(make, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    monkeypatch.setattr(tqdm, "_get_free_pos", interrupted)  # after `disable`, before `pos`
    out = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        make(out)
    gc.collect()
    assert unraisable == [], [u.exc_value for u in unraisable]
    assert out.getvalue() == ""


def test_plain_tqdm_has_the_defect_the_bar_guards_against(monkeypatch):
    # the premise: if tqdm itself stops failing so, the guard can go
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    monkeypatch.setattr(tqdm, "_get_free_pos", interrupted)
    with pytest.raises(KeyboardInterrupt):
        tqdm(total=10, file=io.StringIO())
    gc.collect()
    assert [type(u.exc_value) for u in unraisable] == [AttributeError]


def test_a_bar_that_was_made_still_closes_and_writes(monkeypatch):
    out = io.StringIO()
    with Bar(total=3, file=out, desc="work") as bar:
        bar.update(3)
    assert "work" in out.getvalue() and "3/3" in out.getvalue()
