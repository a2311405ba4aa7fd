"""render_core: Gaussian blendshape head avatars - model, bundle files, deformation, splatting, offline rendering.

The library has no web, queue or global state; the service builds on it.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("blendsplat")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0"
