"""The TypeScript client (clients/js): `npm ci && npm test` there, which compiles it and runs node's test runner
against a real `blendsplat up` of this checkout's venv (clients/js/test/support/server.mjs). Skipped, with the
reason, where node or npm is missing."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

JS = Path(__file__).resolve().parents[1] / "clients" / "js"


@pytest.mark.slow
def test_npm_ci_and_npm_test_pass():
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
    out = subprocess.run([npm, "test"], cwd=JS, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "# fail 0" in out.stdout, out.stdout[-2000:]
