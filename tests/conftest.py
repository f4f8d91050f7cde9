"""Shared pytest fixtures."""

from __future__ import annotations

import signal
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


def pytest_configure(config):
    """Let SIGINT reach the renders the tests start. Many tests press Ctrl-C on a render as a
    user does in a terminal; a suite started in the background by a shell without job
    control (``pytest ... &`` in a script) inherits SIGINT ignored, every process it starts
    would inherit that too, and those tests would wait out their timeouts on renders that
    never heard the signal. A handled signal is not inherited across ``exec``, so the
    children start with the default and install Python's ``KeyboardInterrupt``."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_xdist_auto_num_workers(config):
    """``-n auto`` (pyproject's addopts): one worker per CPU this process may use, at most 4.
    The suite's renders start node processes of their own, so more workers buy little and
    cost memory."""
    from vastray.scene.cpus import available_cpus

    return max(1, min(available_cpus(), 4))


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session):
    """Compile (or load) every render kernel once, in this process, before any test starts
    node processes. A node calls them all before its first hello (``actors.node_warm_up``);
    on a cold numba cache (a fresh install, or CI's bounds-checked run in a fresh cache
    folder) that is about 16 s of compiling a process, and 8 nodes doing it side by side on
    2 cores would take a minute, more than many tests' join timeouts. Done once, by the
    controller (xdist's workers start after it)."""
    if hasattr(session.config, "workerinput"):
        return
    from vastray.actors.node_warm_up import warm_node

    warm_node()


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
