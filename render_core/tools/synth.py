"""Random but well-formed avatars for the commands (``bundle synth``, bench, demo): the generator itself lives in
the library, :mod:`render_core.synthetic`, because runtime code (self-checks, warm-up) uses it too and runtime
code never imports the tools."""

from __future__ import annotations

from ..facemodel.synthetic import synth_avatar

__all__ = ["synth_avatar"]
