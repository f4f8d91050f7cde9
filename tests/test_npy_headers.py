"""Every ``.npy`` header vastray parses is parsed under ``manifest.NPY_HEADERS``: numpy parses
headers with ``ast.literal_eval``, and CPython 3.11 keeps the AST constructor's recursion depth
in state threads share (python/cpython#106905), so a render worker and the preloader parsing
at once failed a domain load with "SystemError: AST constructor recursion depth mismatch"
(CI, 2026-11-29). The race itself is too rare to provoke in a test; this checks the guard is
on every path that reads a header."""

from __future__ import annotations

import numpy as np
import pytest

from vastray.render.imageio import read_image
from vastray.scene import manifest
from vastray.scene.volumes import _read_npy

from scenes import bumpy_scene, write_store


@pytest.fixture
def header_parses(monkeypatch) -> list[bool]:
    """Whether the lock was held at each header numpy parsed (its one parser,
    ``_read_array_header``, under ``np.load`` and the public readers alike)."""
    try:
        from numpy.lib import _format_impl as impl  # numpy 2
    except ImportError:  # numpy 1
        impl = np.lib.format
    held: list[bool] = []
    original = impl._read_array_header

    def parse(*args, **kwargs):
        held.append(manifest.NPY_HEADERS.locked())
        return original(*args, **kwargs)

    monkeypatch.setattr(impl, "_read_array_header", parse)
    return held


def test_domain_loads_read_and_mapped_parse_headers_under_the_lock(tmp_path, header_parses):
    store = write_store(tmp_path / "s.store", bumpy_scene())
    store.load_domain(0, mmap=False)
    store.load_domain(0, mmap=True)
    assert header_parses and all(header_parses)


def test_npy_images_and_volumes_parse_headers_under_the_lock(tmp_path, header_parses):
    np.save(tmp_path / "image.npy", np.zeros((2, 3, 3), np.float32))
    np.save(tmp_path / "volume.npy", np.zeros((4, 4, 4), np.float32))
    read_image(tmp_path / "image.npy")
    _read_npy(tmp_path / "volume.npy")
    assert len(header_parses) == 2 and all(header_parses)
