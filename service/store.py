"""The bundle store: avatar bundles by id, in a local folder (``<data_dir>/bundles/<id>.bundle``).

Uploads are staged in the same folder, fully validated (layout, manifest, digest, finite values) and then renamed
into place atomically, so a reader never sees a partial or invalid bundle and a failed upload leaves nothing.
Bundles are immutable: replacing one writes a new file (processes that mapped the old one keep their copy).

Integrity is paid once, when a bundle enters the store: beside ``<id>.bundle`` the store records what it verified
(``<id>.bundle.verified``: the file's size, the SHA-256 of its header, which holds the content digest, and that
digest). Every replica sharing the folder sees the record; a load whose file still has that size and header
trusts it and skips the full pass (:meth:`BundleStore.verified`). A file replaced behind the store's back (a
different size or header) has no matching record and is fully verified when it is next loaded.

The folder is created once, when it was never there (the first start on an empty data dir). A folder that this
process has seen and that is gone (an unmounted volume, a deleted directory) is an outage, not an empty store: every
call that needs it raises :class:`~service.errors.Unavailable` naming the folder, nothing recreates it, and
:meth:`BundleStore.reachable` stays false (readiness) until it is back. Staged uploads (``.upload-*.tmp``) and the
atomic writers' temporary files left by a killed process are removed at start (:meth:`BundleStore.clean_stale`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from render_core.atomic import atomic_path, publish
from render_core.bundle import BundleMappingError, read_manifest, validate_bundle
from render_core.errors import BundleError

from .errors import InvalidArgument, NotFound, PermissionDenied, ResourceExhausted, Unavailable
from .usage import disk_bytes

ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
SUFFIX = ".bundle"
STAGED_PREFIX = ".upload-"  # <root>/.upload-XXXX.tmp: an upload being received or validated
RECORD = ".verified"  # <id>.bundle.verified: what the store verified (never ends in SUFFIX, so never an id)
OWNER = ".owner"  # <id>.bundle.owner: {"tenant": ..., "public": ...} (service/access/auth.py's ownership rules)
_MAX_HEADER = 100 << 20  # as the bundle reader's limit: a longer header is not a bundle


@dataclass(frozen=True)
class Owner:
    """Who owns an avatar: its tenant (None: no tenant, only admin keys may change it) and whether every key may
    read and stream it (the demo avatar). A bundle without an owner file is ``Owner(None, False)``: admin only."""

    tenant: str | None
    public: bool = False


@dataclass(frozen=True)
class Writer:
    """Who writes an avatar: its tenant (the admin tenant for admin keys and the process itself) and whether it
    holds the admin scope. Every avatar write (the PUT, a training job's commit, the job submission's check)
    goes through :meth:`BundleStore.writable` with one."""

    tenant: str
    admin: bool


def check_id(avatar_id: str, field: str = "avatar_id") -> str:
    if not ID_PATTERN.match(avatar_id or ""):
        raise InvalidArgument(f"{avatar_id!r} is not an avatar id (letters, digits, '.', '_', '-'; at most 128, "
                              "starting with a letter or digit)", field=field)
    return avatar_id


class BundleStore:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self._seen = self.root.is_dir()  # once seen, a missing folder is an outage, never recreated

    def ensure(self) -> None:
        """Create the folder if it was never there (first start); Unavailable when it existed and is gone."""
        if not self.root.is_dir():
            self._check_present()
            self.root.mkdir(parents=True, exist_ok=True)
        self._seen = True

    def reachable(self) -> bool:
        return self.problem() is None

    def problem(self) -> str | None:
        """Why the store is not usable (readiness says it), or None."""
        if not self.root.is_dir():
            return f"the bundle store folder {self.root} is missing"
        if not os.access(self.root, os.R_OK | os.W_OK | os.X_OK):
            return f"the bundle store folder {self.root} is not readable and writable by this process"
        self._seen = True
        return None

    def _check_present(self) -> bool:
        """Whether the folder is there; Unavailable when it was there before (False: never created yet)."""
        if self.root.is_dir():
            self._seen = True
            return True
        if self._seen:
            raise Unavailable(f"the bundle store folder {self.root} is missing (it is not recreated; the avatars "
                              "are unavailable until it is back)", field="bundle_store")
        return False

    def path(self, avatar_id: str) -> Path:
        return self.root / f"{check_id(avatar_id)}{SUFFIX}"

    def ids(self) -> list[str]:
        if not self._check_present():
            return []
        return sorted(p.name[: -len(SUFFIX)] for p in self.root.iterdir()
                      if p.name.endswith(SUFFIX) and ID_PATTERN.match(p.name[: -len(SUFFIX)]))

    def existing(self, avatar_id: str) -> Path:
        """The bundle's path; NotFound when the store has no such avatar (Unavailable when the store is gone)."""
        path = self.path(avatar_id)
        if not path.is_file():
            self._check_present()
            # never a listing of the store: it would show other tenants' ids (GET /v1/avatars lists the caller's)
            raise NotFound(f"no avatar {avatar_id!r} in the bundle store (GET /v1/avatars lists the avatars this key "
                           "may see)", field="avatar_id")
        return path

    def manifest(self, avatar_id: str) -> dict:
        return read_manifest(self.existing(avatar_id))

    def staging(self) -> tuple[int, Path]:
        """An open file descriptor and path for an upload in progress (same folder: the rename is atomic).
        Unavailable when the folder is gone (it is created only if it never existed)."""
        self.ensure()
        fd, name = tempfile.mkstemp(prefix=STAGED_PREFIX, suffix=".tmp", dir=self.root)
        return fd, Path(name)

    def staging_path(self) -> Path:
        """A fresh path for an upload in progress, not yet created (the intake creates it exclusively; same
        folder: the rename is atomic)."""
        self.ensure()
        return self.root / f"{STAGED_PREFIX}{os.urandom(8).hex()}.tmp"

    def clean_stale(self, older_than: float) -> list[str]:
        """Remove the temporary files a killed process left in the store (staged uploads, the atomic writers'
        ``.<name>.<hex>.tmp``) not modified for ``older_than`` seconds: an upload in progress elsewhere (another
        replica sharing the folder) writes more often than its body timeout, so it is never taken. The names
        removed."""
        if not self.root.is_dir():
            return []
        cutoff, removed = time.time() - older_than, []
        for p in self.root.iterdir():
            if not (p.name.startswith(".") and p.name.endswith(".tmp")):
                continue
            try:
                if p.is_file() and not p.is_symlink() and p.stat().st_mtime < cutoff:
                    p.unlink()
                    removed.append(p.name)
            except FileNotFoundError:
                pass  # someone else finished or removed it
        return removed

    def writable(self, avatar_id: str, writer: Writer) -> tuple[Owner, bool]:
        """The one ownership rule of an avatar write: ``writer`` may write ``avatar_id`` when the id is free, or
        the avatar is its tenant's, or it is an admin (PermissionDenied otherwise). The owner after the write: the
        writer's tenant, except that an admin replacing an existing avatar keeps that avatar's owner (an admin
        fixing a tenant's avatar does not take it). Returns (that owner, whether the avatar exists)."""
        existing = self.owner_if_exists(check_id(avatar_id))
        if existing is None:
            return Owner(writer.tenant), False
        if writer.admin:
            return existing, True
        if existing.tenant is None or existing.tenant != writer.tenant:
            raise PermissionDenied(f"avatar {avatar_id!r} belongs to another tenant"
                                   + (" (public: only an admin key may change it)" if existing.tenant is None
                                      or existing.public else ""), field="authorization")
        return existing, True

    def put(self, staged: Path, avatar_id: str, writer: Writer) -> tuple[dict, bool]:
        """Validate a staged bundle and publish it as ``avatar_id`` for ``writer`` (:meth:`writable`'s rule, checked
        again just before the commit); the manifest and whether it replaced an avatar. The staged file is gone
        after, whatever happens."""
        try:
            owner, existed = self.writable(avatar_id, writer)
        except BaseException:
            staged.unlink(missing_ok=True)
            raise
        return self.commit(staged, avatar_id, owner), existed

    def commit(self, staged: Path, avatar_id: str, owner: Owner | None = None) -> dict:
        """Validate a staged upload, move it into place as ``avatar_id`` and record it as verified (and its
        ``owner``, when given); the staged file is gone after."""
        try:
            target = self.path(avatar_id)
            try:
                manifest = validate_bundle(staged)
            except BundleMappingError as e:  # this machine's limit, not the upload's fault
                raise ResourceExhausted(f"the bundle cannot be checked here: {e.detail}", field="bundle") from None
            except BundleError as e:
                raise InvalidArgument(f"not a valid avatar bundle: {e}", field="bundle") from None
            identity = _identity(staged)
            if owner is not None:  # before the bundle: a new bundle is never visible without its owner
                self.set_owner(avatar_id, owner)
            publish(staged, target)
            self._record(target, identity, manifest)
            return manifest
        finally:
            staged.unlink(missing_ok=True)

    def adopt(self, avatar_id: str) -> dict:
        """Fully validate a bundle written into the store by this process (the demo avatar) and record it."""
        path = self.existing(avatar_id)
        identity = _identity(path)
        manifest = validate_bundle(path)
        self._record(path, identity, manifest)
        return manifest

    def owner(self, avatar_id: str) -> Owner:
        """The avatar's owner (``Owner(None, False)`` when it has no owner file: admin keys only)."""
        try:
            data = json.loads(self.path(avatar_id).with_name(f"{avatar_id}{SUFFIX}{OWNER}").read_text("utf-8"))
            tenant = data.get("tenant")
            return Owner(tenant if isinstance(tenant, str) else None, data.get("public") is True)
        except (OSError, ValueError, AttributeError):
            return Owner(None, False)

    def owner_if_exists(self, avatar_id: str) -> Owner | None:
        """The owner of an avatar in the store, None when there is no such avatar."""
        return self.owner(avatar_id) if self.path(avatar_id).is_file() else None

    def set_owner(self, avatar_id: str, owner: Owner) -> None:
        with atomic_path(self.path(avatar_id).with_name(f"{avatar_id}{SUFFIX}{OWNER}")) as tmp:
            tmp.write_text(json.dumps({"tenant": owner.tenant, "public": owner.public}), encoding="utf-8")

    def sidecars(self, avatar_id: str) -> list[Path]:
        """The files kept beside a bundle (verification record, owner): removed with it."""
        path = self.path(avatar_id)
        return [path.with_name(path.name + RECORD), path.with_name(path.name + OWNER)]

    def tenant_bytes(self, tenant: str) -> int:
        """Bytes on disk of the bundles ``tenant`` owns (its storage quota counts them: :mod:`service.usage`)."""
        total = 0
        for avatar_id in self.ids():
            if self.owner(avatar_id).tenant == tenant:
                with contextlib.suppress(OSError):
                    total += disk_bytes(self.path(avatar_id).stat())
        return total

    def verified(self, path: Path) -> bool:
        """Whether ``path`` is the file the store verified when it entered (same size and header as recorded):
        a load may then skip the digest and finiteness pass. False for anything else, including no record."""
        try:
            record = json.loads(path.with_name(path.name + RECORD).read_text(encoding="utf-8"))
            return record == {**_identity(path), "digest": record.get("digest")}
        except (OSError, ValueError, TypeError):
            return False

    def _record(self, path: Path, identity: dict, manifest: dict) -> None:
        with atomic_path(path.with_name(path.name + RECORD)) as tmp:
            tmp.write_text(json.dumps({**identity, "digest": manifest.get("digest")}), encoding="utf-8")


def _identity(path: Path) -> dict:
    """A bundle file's size and the SHA-256 of its header (length prefix, tensor table and manifest with the
    content digest): what tells one bundle file from another without reading its data."""
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        prefix = f.read(8)
        n = int.from_bytes(prefix, "little") if len(prefix) == 8 else 0
        header = prefix + f.read(min(n, _MAX_HEADER))
    return {"size": size, "header_sha256": hashlib.sha256(header).hexdigest()}
