"""The TypeScript client (clients/js): `npm ci && npm test` there, which compiles it and runs node's test runner
against a real `blendsplat up` of this checkout's venv (clients/js/test/support/server.mjs); and the copy the
server ships (service/static/client/, what the /demo and /jobs pages import) is exactly what `npm run build:static`
makes of the sources. Skipped, with the reason, where node or npm is missing."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
JS = ROOT / "clients" / "js"
SHIPPED = ROOT / "service" / "static" / "client"


def _npm_ci() -> tuple[str, dict[str, str]]:
    """npm and an environment without BLENDSPLAT_ variables, after `npm ci` (skips where it cannot run)."""
    npm, node = shutil.which("npm"), shutil.which("node")
    if npm is None or node is None:
        pytest.skip("node and npm are needed for clients/js (e.g. apt-get install -y nodejs npm; node >= 20.10)")
    version = subprocess.run([node, "--version"], capture_output=True, text=True).stdout.strip().lstrip("v")
    if tuple(int(p) for p in version.split(".")[:2]) < (20, 10):
        pytest.skip(f"node {version} is too old for clients/js (>= 20.10: --experimental-websocket)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("BLENDSPLAT_")}  # it starts its own server
    ci = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=JS, env=env, capture_output=True, text=True,
                        timeout=300)
    if ci.returncode != 0 and "ENOTFOUND" in ci.stderr + ci.stdout:
        pytest.skip(f"npm ci cannot reach the registry: {ci.stderr[-300:]}")
    assert ci.returncode == 0, ci.stdout[-2000:] + ci.stderr[-2000:]
    return npm, env


def test_the_shipped_module_is_the_build_of_the_sources(tmp_path):
    """`npm run build:static` (tsc -p tsconfig.static.json) into a temporary folder: byte for byte the committed
    service/static/client/*.js, and no file more or less (else: run it in clients/js and commit the result)."""
    npm, env = _npm_ci()
    out = subprocess.run([npm, "run", "--silent", "build:static", "--", "--outDir", str(tmp_path)], cwd=JS, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    built = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    shipped = {p.name: p.read_bytes() for p in SHIPPED.glob("*.js")}
    assert built and all(name.endswith(".js") for name in built), sorted(built)
    assert sorted(shipped) == sorted(built), "run `npm run build:static` in clients/js and commit service/static/client"
    stale = [name for name in built if built[name] != shipped[name]]
    assert not stale, f"{stale} differ from the sources' build: run `npm run build:static` in clients/js"


@pytest.mark.slow
def test_npm_ci_and_npm_test_pass():
    npm, env = _npm_ci()
    out = subprocess.run([npm, "test"], cwd=JS, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "# fail 0" in out.stdout, out.stdout[-2000:]
