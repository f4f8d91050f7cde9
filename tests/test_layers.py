"""The layering of docs/DESIGN.md, checked on the source: data flows files → scene → render →
schedule → actors/transport, and nothing below ``actors/`` knows about asyncio or sockets, so
the scheduling policies can be driven without them (by unit tests, by a simulator)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: folder -> the vastray layers its modules may import (besides their own).
ALLOWED = {
    "scene": set(),
    "render": {"scene"},
    "schedule": {"scene", "render"},
    "transport": set(),
}
#: leaf modules (they import no other vastray module) every layer may use: the error types
#: users catch, and the process-memory reader.
LEAVES = {"vastray.scene.errors": ROOT / "scene/errors.py",
          "vastray.processes": ROOT / "src/vastray/processes.py"}
#: documented exceptions: ``vastray.render(...)`` forwards to the API, imported when called.
EXCEPTIONS = {("render/__init__.py", "vastray.api")}
#: third-party modules of the runtime layers, which no policy or kernel may use.
RUNTIME_ONLY = {"asyncio", "zmq", "uvloop", "msgpack"}


def imports(path: Path) -> set[str]:
    """Every module ``path`` imports (absolute names; at any depth, lazy imports included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


@pytest.mark.parametrize("folder", sorted(ALLOWED))
def test_a_layer_imports_only_the_layers_below_it(folder):
    wrong = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for name in imports(path):
            parts = name.split(".")
            if name in LEAVES or (str(path.relative_to(ROOT)), name) in EXCEPTIONS:
                continue
            if parts[0] == "vastray" and len(parts) > 1 and parts[1] in (
                    "scene", "render", "schedule", "transport", "actors"):
                if parts[1] != folder and parts[1] not in ALLOWED[folder]:
                    wrong.append(f"{path.relative_to(ROOT)} imports {name}")
            elif parts[0] == "vastray" and len(parts) > 1 and folder != "transport":
                wrong.append(f"{path.relative_to(ROOT)} imports {name}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("folder", ["scene", "render", "schedule"])
def test_nothing_below_actors_knows_asyncio_or_sockets(folder):
    wrong = [f"{path.relative_to(ROOT)} imports {name}"
             for path in sorted((ROOT / folder).rglob("*.py"))
             for name in imports(path) if name.split(".")[0] in RUNTIME_ONLY]
    assert not wrong, "\n".join(wrong)


def test_the_leaves_every_layer_may_use_import_no_other_vastray_module():
    for name, path in LEAVES.items():
        assert not [i for i in imports(path) if i.startswith("vastray")], name
