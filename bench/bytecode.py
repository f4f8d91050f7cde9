"""Node processes started by a bench start as those of an installed vastray do: from compiled
bytecode.

``pip install`` (not editable) compiles every module's bytecode as it installs; a checkout
installed with ``pip install -e`` leaves it to Python, which writes ``__pycache__`` on first
import unless told not to (``PYTHONDONTWRITEBYTECODE``, ``python -B``, a read-only tree). Told
not to, every node process compiles vastray's source again as it imports it: 557 modules'
``compile`` took 0.33 s of a coordinator's CPU here, and each node pays as much before its
first hello, so 8 nodes sharing 2 cores started a job in 7.4-7.6 s where compiled bytecode
starts it in 6.4-6.6 s (session 74, ``render_distributed`` of the turbine-blade scan on 8
nodes). A bench that starts hundreds of node processes (``bench/simulate.py``: about 60 jobs)
compiles the bytecode first, once, so its minutes go where a user's would."""

from __future__ import annotations

import compileall
import importlib.util

#: vastray's packages whose folders hold its modules (the checkout maps the top-level
#: folders into the package: ``pyproject.toml``'s ``package-dir``).
PACKAGES = ("vastray", "vastray.actors", "vastray.render", "vastray.scene",
            "vastray.schedule", "vastray.transport")


def compile_vastray() -> bool:
    """Write the bytecode of every vastray module whose bytecode is missing or stale (the
    ones up to date are left alone: about a second when all are). Returns whether every
    folder compiled (a read-only one does not, and its nodes compile as they import)."""
    done = True
    for name in PACKAGES:
        spec = importlib.util.find_spec(name)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            done = bool(compileall.compile_dir(folder, quiet=1)) and done
    return done
