"""The layering is a checked contract: pyproject.toml's import-linter contracts hold on this tree, and they break
when the layering is broken (a copy of the sources with one bad import)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONTRACTS = {c["id"]: c["name"] for c in tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
             ["contracts"]}

# lint-imports on the working directory's packages: an editable install's import hook would resolve render_core
# and service to the checkout whatever the directory, so only the standard finders are kept.
_LINT_HERE = """
import sys
from importlinter.cli import lint_imports
sys.meta_path[:] = [f for f in sys.meta_path if f.__module__.startswith(("_frozen_importlib", "importlib"))]
sys.exit(lint_imports(no_cache=True, no_logo=True))
"""


# wide enough that rich, writing to a pipe, never wraps a contract's line
ENV = {**os.environ, "COLUMNS": "400"}


def _lint_imports() -> Path:
    path = Path(sys.executable).with_name("lint-imports")
    found = path if path.exists() else shutil.which("lint-imports")
    if found is None:
        pytest.fail("lint-imports is not installed (pip install -e '.[dev]')")
    return Path(found)


def _status(output: str, contract_id: str) -> str:
    """KEPT or BROKEN: the contract's line in lint-imports' summary."""
    name = CONTRACTS[contract_id]
    lines = [line for line in output.splitlines() if line.startswith(name + " ")]
    assert lines, f"no line for {name!r} in:\n{output}"
    return lines[0].rsplit(" ", 1)[1]


def test_the_tree_keeps_every_contract():
    out = subprocess.run([_lint_imports(), "--no-cache", "--no-logo"], cwd=ROOT, env=ENV, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert {c: _status(out.stdout, c) for c in CONTRACTS} == dict.fromkeys(CONTRACTS, "KEPT")


@pytest.mark.parametrize(("module", "code", "broken", "named"), [
    # the library reaching into the processes
    ("render_core/errors.py", "\nimport service  # injected\n", "library-not-service",
     "render_core.errors -> service"),
    # a runtime module using training, even from inside a function
    ("render_core/camera.py", "\n\ndef _injected():\n    from .train import presets  # noqa: F401\n",
     "library-layers", "render_core.camera -> render_core.train.presets"),
    # tools are the top layer: runtime code never imports them
    ("render_core/raster/native.py", "\nfrom ..tools import synth  # injected\n", "library-layers",
     "render_core.raster.native -> render_core.tools.synth"),
    # the stored layout knowing the model that holds it (the circle avatar <-> packed, closed again)
    ("render_core/packed.py", "\n\ndef _injected():\n    from .avatar import Avatar  # noqa: F401\n",
     "avatar-model-layers", "render_core.packed -> render_core.avatar"),
    # a new module must be placed in a layer
    ("render_core/unplaced.py", "", "library-layers", "render_core.unplaced"),
    # a transport reaching past the engine into the library
    ("service/http/avatars.py", "\nfrom render_core import deform  # injected\n", "transports-through-the-engine",
     "service.http.avatars -> render_core.deform"),
    # settings reading a part of the service
    ("service/settings.py", "\n\ndef _injected():\n    from .access import keys  # noqa: F401\n",
     "settings-import-nothing", "service.settings -> service.access.keys"),
    # a lower wing reaching up: the store importing the engine
    ("service/store.py", "\n\ndef _injected():\n    from .engine import Engine  # noqa: F401\n", "service-wings",
     "service.store -> service.engine"),
])
def test_a_broken_layering_breaks_its_contract(tmp_path, module, code, broken, named):
    def sources_only(folder: str, names: list[str]) -> list[str]:
        return [n for n in names if n == "__pycache__" or not (n.endswith(".py") or Path(folder, n).is_dir())]

    for package in ("render_core", "service"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=sources_only)
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    target = tmp_path / module
    target.write_text((target.read_text() if target.exists() else "") + code)

    out = subprocess.run([sys.executable, "-c", _LINT_HERE], cwd=tmp_path, env=ENV, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode != 0, out.stdout + out.stderr
    status = {c: _status(out.stdout, c) for c in CONTRACTS}
    assert status == {c: "BROKEN" if c == broken else "KEPT" for c in CONTRACTS}, out.stdout
    assert named in out.stdout, out.stdout
