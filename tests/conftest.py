"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real third-party test data folder ``<repo>/../shared/data`` (see its README.md).

    Skips the test when the folder is absent (e.g. a checkout without the shared data).
    """
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA} (expected <repo>/../shared/data)")
    return SHARED_DATA


def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (pyproject's addopts): one worker per CPU this process may use, at most 4.
    The suite's renders start node processes of their own, so more workers buy little and
    cost memory."""
    from vastray.scene.cpus import available_cpus

    return max(1, min(available_cpus(), 4))


def pytest_collection_modifyitems(config, items):
    """Skip ``@pytest.mark.slow`` tests unless a ``-m`` expression selects by marker."""
    if config.option.markexpr:
        return
    skip = pytest.mark.skip(reason="slow test; run with -m slow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def reload_binding():
    """The Embree binding loaded afresh for the test, and forgotten after it."""
    from scenes import forget_binding

    forget_binding()
    yield
    forget_binding()
