"""render_core: Gaussian blendshape head avatars - model, bundle files, deformation, splatting, training.

The library has no web, queue or global state; the service builds on it. The names below are its public API::

    from render_core import read_bundle, Frame, deform, render, orbit

    avatar = read_bundle("head.bundle")
    frame = Frame.from_params(avatar, expression={"jawOpen": 0.8})
    out = render(deform(avatar, frame), orbit([0.0], width=512, height=512), mode=avatar.raster_mode)

Layout (docs/architecture.md): the avatar model and its file at the top (avatar, gaussians, packed, bundle, camera,
deform, drive, renderer, rotation, sh, errors, atomic, synthetic); rasterizer backends in ``raster/`` (C++ kernels
in ``native/``); stream codecs and file writers in ``media/``; face models in ``facemodel/``; datasets in
``data/``; training in ``train/``; evaluation in ``evaluation/``; the command-line tools in ``tools/``. Each of
the last four may import only what comes before it (pyproject.toml's import-linter contracts).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("blendsplat")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0"

from .avatar import Avatar, Gaussians
from .bundle import read_bundle, read_manifest, validate_bundle, write_bundle
from .camera import Cameras, front_camera, look_at, orbit
from .deform import Frame, Splats, blend, deform, shade, skin  # the function ``deform`` shadows its module's name
from .drive import read_drive_file
from .errors import BlendsplatError, BundleError, DatasetError, FaceModelError, FrameError, ShapeError
from .raster import RasterOutput, render
from .renderer import AvatarRenderer

__all__ = [
    "Avatar", "AvatarRenderer", "BlendsplatError", "BundleError", "Cameras", "DatasetError", "FaceModelError",
    "Frame", "FrameError", "Gaussians", "RasterOutput", "ShapeError", "Splats", "blend", "deform", "front_camera",
    "look_at", "orbit", "read_bundle", "read_drive_file", "read_manifest", "render", "shade", "skin",
    "validate_bundle", "write_bundle",
]
