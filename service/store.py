"""The bundle store: avatar bundles by id, in a local folder (``<data_dir>/bundles/<id>.bundle``).

Uploads are staged in the same folder, fully validated (layout, manifest, digest, finite values) and then renamed
into place atomically, so a reader never sees a partial or invalid bundle and a failed upload leaves nothing.
Bundles are immutable: replacing one writes a new file (processes that mapped the old one keep their copy).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

from render_core.atomic import publish
from render_core.bundle import read_manifest, validate_bundle
from render_core.errors import BundleError

from .errors import InvalidArgument, NotFound

ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
SUFFIX = ".bundle"


def check_id(avatar_id: str, field: str = "avatar_id") -> str:
    if not ID_PATTERN.match(avatar_id or "") or avatar_id.endswith(".tmp"):
        raise InvalidArgument(f"{avatar_id!r} is not an avatar id (letters, digits, '.', '_', '-'; at most 128, "
                              "starting with a letter or digit)", field=field)
    return avatar_id


class BundleStore:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def ensure(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)

    def reachable(self) -> bool:
        return self.root.is_dir() and os.access(self.root, os.R_OK | os.W_OK | os.X_OK)

    def path(self, avatar_id: str) -> Path:
        return self.root / f"{check_id(avatar_id)}{SUFFIX}"

    def ids(self) -> list[str]:
        if not self.root.is_dir():
            return []
        return sorted(p.name[: -len(SUFFIX)] for p in self.root.iterdir()
                      if p.name.endswith(SUFFIX) and ID_PATTERN.match(p.name[: -len(SUFFIX)]))

    def existing(self, avatar_id: str) -> Path:
        """The bundle's path; NotFound when the store has no such avatar."""
        path = self.path(avatar_id)
        if not path.is_file():
            known = self.ids()
            raise NotFound(f"no avatar {avatar_id!r} in the bundle store"
                           + (f" (avatars: {', '.join(known[:20])})" if known else " (the store is empty)"),
                           field="avatar_id")
        return path

    def manifest(self, avatar_id: str) -> dict:
        return read_manifest(self.existing(avatar_id))

    def staging(self) -> tuple[int, Path]:
        """An open file descriptor and path for an upload in progress (same folder: the rename is atomic)."""
        self.ensure()
        fd, name = tempfile.mkstemp(prefix=".upload-", suffix=".tmp", dir=self.root)
        return fd, Path(name)

    def commit(self, staged: Path, avatar_id: str) -> dict:
        """Validate a staged upload and move it into place as ``avatar_id``; the staged file is gone after."""
        try:
            target = self.path(avatar_id)
            try:
                manifest = validate_bundle(staged)
            except BundleError as e:
                raise InvalidArgument(f"not a valid avatar bundle: {e}", field="bundle") from None
            publish(staged, target)
            return manifest
        finally:
            staged.unlink(missing_ok=True)
