"""Typed errors of render_core.

Every error a caller can cause with bad input derives from :class:`BlendsplatError`, so transports map them to
gRPC status codes and HTTP statuses in one place. Each names what is wrong (``field``) in its message.
"""

from __future__ import annotations


class BlendsplatError(Exception):
    """Base class of the errors render_core raises on bad input."""

    def __init__(self, message: str, *, field: str | None = None):
        self.field = field
        self.detail = message  # without the field (for replies that carry the field separately)
        super().__init__(f"{field}: {message}" if field else message)


class BundleError(BlendsplatError):
    """An avatar bundle file is malformed: truncated, tampered, wrong shapes, non-finite values, bad manifest,
    or a schema version this build cannot read. ``field`` names the offending tensor or manifest key."""


class FrameError(BlendsplatError):
    """Frame parameters (expression coefficients, joint rotations, eyelids, camera) are invalid for an avatar.
    The message lists what would be valid."""


class ShapeError(BlendsplatError):
    """A tensor argument has the wrong shape, dtype or non-finite values."""


class FaceModelError(BlendsplatError):
    """A face-model file or its evaluation inputs are invalid (``field`` names the offending array or key)."""


class DatasetError(BlendsplatError):
    """A tracked-video dataset is malformed: missing or unreadable frames, mismatched counts, bad tracking."""


class CodecError(BlendsplatError):
    """Stream codec settings are invalid: an unknown codec, a frame size, quality or frame rate out of range, or
    a message a codec cannot decode as asked. ``field`` names the setting (``codec``, ``width``, ``height``,
    ``quality``, ``fps``)."""


class OptionError(BlendsplatError, ValueError):
    """An option of a command or library call is invalid: a backend, precision, device, output format or a count
    out of range. ``field`` names the option. Also a :class:`ValueError`, which these options raised before."""


class TrackingError(BlendsplatError):
    """Tracking a video failed on its input: not a video (``video``), a stream corrupt halfway (``video``), over a
    limit (``duration``, ``resolution``, ``frames``), a bad option (``fps``, ``crop``, ``size``, ``detector``,
    ``photometric``), no face found (``face``), or the shipped tracking models missing or altered (``model``).
    ``field`` names which."""
