"""The README's examples run as written."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_block(heading: str) -> str:
    text = README.read_text(encoding="utf-8")
    section = text.split(heading, 1)[1]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, f"no python block under {heading!r} in README.md"
    return match.group(1)


def test_library_example_runs_as_written(tmp_path, monkeypatch):
    write_bundle(synth_avatar(gaussians=400, blendshapes=6, seed=2), tmp_path / "head.bundle")
    monkeypatch.chdir(tmp_path)
    code = _python_block("### Library")
    scope: dict = {}
    exec(compile(code, "README.md:Library", "exec"), scope)  # noqa: S102 - our own README
    out = scope["out"]
    assert out.rgb.shape == (4, 512, 512, 3) and out.alpha.shape == (4, 512, 512)
    assert torch.isfinite(out.rgb).all() and out.alpha.amax() > 0.5  # the avatar is in view
