"""`blendsplat bench load`: what it costs to bring one avatar from the bundle store to its first frame.

The bundle is committed to a temporary store (as an upload is), then loaded in fresh processes so that memory
and caches start clean: ``cold`` after the file is flushed and dropped from the page cache
(``posix_fadvise(DONTNEED)``), ``warm`` with the file in the page cache. Each load is the service's own cache-miss
path (:func:`service.cache.read_entry`, trusting the store's record of the verification done at commit) followed
by one frame at the avatar's default camera. ``verify_ms`` is the full verification (digest, shapes, finite
values) that a bundle loaded from outside a store pays.

Memory, each the growth of resident memory (anonymous plus file-backed pages) from before the load to after the
first frame, each reading taken after freed heap is handed back to the system (``malloc_trim``), so that both
count memory in use and a load can neither hide in nor be charged for the allocator's spare:

- ``resident_bytes``: what the avatar itself costs a serving replica. Before the load the process renders one
  warm-up frame of a synthetic avatar with as many Gaussians at the same size, as a replica does at start-up, so the
  render workspace (per-thread splat and tile buffers, reused by every avatar) is already sized;
- ``resident_fresh_process_bytes``: the same in a process that renders nothing before, so the workspace of its
  first frame counts too.

``--vs-v1`` also rewrites the avatar as a schema-1 (dense) bundle and reports the same figures for it under
``"v1"``, with the ratios v1 / this file; in the file's precision, or fp16 for an int8 file (schema 1 has no int8).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from render_core.bundle import read_bundle, stored_schema_version, validate_bundle, write_bundle

from .cache import read_entry
from .store import BundleStore

AVATAR_ID = "bench"


def _trim_heap() -> None:
    """Hand freed heap back to the system (glibc ``malloc_trim``), so a reading counts memory in use, not the
    allocator's spare."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: freed heap may stay resident, which only overstates the growth
        pass


def _resident_bytes() -> int:
    """This process's resident anonymous plus file-backed memory in use (Linux /proc), after :func:`_trim_heap`."""
    _trim_heap()
    fields = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("RssAnon", "RssFile"):
            fields[name] = int(value.split()[0]) * 1024
    return sum(fields.values())


def _drop_from_page_cache(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def _warm_workspace(gaussians: int, size: int, backend: str | None, threads: int) -> None:
    """Render one frame of a synthetic avatar of ``gaussians`` Gaussians (a replica's warm-up frame)."""
    import gc

    import torch

    from render_core.deform import Frame
    from render_core.drive import default_camera
    from render_core.renderer import AvatarRenderer
    from render_core.tools.synth import synth_avatar

    avatar = synth_avatar(gaussians, 1, seed=0)
    AvatarRenderer(avatar, backend, threads=threads).render(
        Frame.from_params(avatar, expression=torch.zeros(1, 1)), default_camera(avatar, size, size))
    del avatar
    gc.collect()


def load_once(path: Path, size: int, backend: str | None, threads: int, warm_workspace: bool = True) -> dict:
    """One load from the store and one frame, in this process: stage milliseconds and the resident growth."""
    import torch

    from render_core.bundle import read_manifest
    from render_core.deform import Frame
    from render_core.drive import default_camera
    from render_core.raster import native

    if native.available():
        native.simd_choice(None)  # the one-off SIMD self-check belongs to process start, not to a load
    if warm_workspace:
        counts = read_manifest(path)["counts"]
        _warm_workspace(counts["gaussians"] + counts["mouth"], size, backend, threads)
    before = _resident_bytes()
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    verify = not BundleStore(path.parent).verified(path)  # the store's own decision, as the cache makes it
    entry = read_entry(AVATAR_ID, path, backend, threads, verify=verify, seconds=seconds)
    t1 = time.perf_counter()
    avatar = entry.avatar
    frame = Frame.from_params(avatar, expression=torch.zeros(1, avatar.num_expressions))
    entry.renderer.render(frame, default_camera(avatar, size, size))
    t2 = time.perf_counter()
    ms = {"read": seconds["read"] * 1e3, "renderer": seconds["renderer"] * 1e3, "first_frame": (t2 - t1) * 1e3,
          "total": (t2 - t0) * 1e3}
    return {"ms": {k: round(v, 2) for k, v in ms.items()}, "resident_bytes": _resident_bytes() - before,
            "backend": entry.renderer.backend, "verified_on_load": verify}


def _load_in_fresh_process(path: Path, size: int, backend: str | None, threads: int,
                           warm_workspace: bool = True) -> dict:
    out = path.with_name("figures.json")
    args = json.dumps({"path": str(path), "size": size, "backend": backend, "threads": threads, "out": str(out),
                       "warm_workspace": warm_workspace})
    proc = subprocess.run([sys.executable, "-m", "service.bench_load", args], capture_output=True, text=True,
                          check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"the load process failed (exit {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return json.loads(out.read_text())


def bench_load(bundle: str | os.PathLike, *, size: int = 512, backend: str | None = None, threads: int = 0,
               vs_v1: bool = False) -> dict:
    """Cold and warm loads of ``bundle`` from a temporary store (module docstring); a JSON-ready dict."""
    bundle = Path(bundle)
    report = _bench_file(bundle, size, backend, threads)
    report = {"benchmark": "load", "bundle": str(bundle), **report}
    if vs_v1:
        with tempfile.TemporaryDirectory(prefix="blendsplat-bench-load-v1-") as tmp:
            v1 = Path(tmp) / "v1.bundle"
            dense = "fp16" if report["precision"] == "int8" else report["precision"]  # schema 1 has no int8
            write_bundle(read_bundle(bundle), v1, precision=dense, schema_version=1)
            report["v1"] = _bench_file(v1, size, backend, threads)
        old = report["v1"]
        report["v1_over_this"] = {
            "file_bytes": round(old["file_bytes"] / report["file_bytes"], 2),
            "resident_bytes": round(old["resident_bytes"] / max(report["resident_bytes"], 1), 2),
            "cold_total": round(old["cold_ms"]["total"] / report["cold_ms"]["total"], 2),
            "warm_total": round(old["warm_ms"]["total"] / report["warm_ms"]["total"], 2),
            "verify": round(old["verify_ms"] / report["verify_ms"], 2),
        }
    return report


def _bench_file(bundle: Path, size: int, backend: str | None, threads: int) -> dict:
    t0 = time.perf_counter()
    manifest = validate_bundle(bundle)
    verify_ms = (time.perf_counter() - t0) * 1e3
    with tempfile.TemporaryDirectory(prefix="blendsplat-bench-load-") as tmp:
        store = BundleStore(Path(tmp) / "bundles")
        fd, staged = store.staging()
        with os.fdopen(fd, "wb") as out, open(bundle, "rb") as src:
            shutil.copyfileobj(src, out, 1 << 20)
        store.commit(staged, AVATAR_ID)
        path = store.path(AVATAR_ID)
        _drop_from_page_cache(path)
        cold = _load_in_fresh_process(path, size, backend, threads)
        warm = _load_in_fresh_process(path, size, backend, threads)
        fresh = _load_in_fresh_process(path, size, backend, threads, warm_workspace=False)
    return {
        "schema_version": stored_schema_version(bundle),
        "precision": manifest.get("precision"), "gaussians": manifest["counts"]["gaussians"],
        "mouth_gaussians": manifest["counts"]["mouth"], "size": size, "backend": cold["backend"],
        "file_bytes": bundle.stat().st_size, "resident_bytes": cold["resident_bytes"],
        "resident_fresh_process_bytes": fresh["resident_bytes"],
        "cold_ms": cold["ms"], "warm_ms": warm["ms"], "verify_ms": round(verify_ms, 2),
        "verified_on_load": cold["verified_on_load"],
    }


if __name__ == "__main__":  # the fresh process of one load: JSON arguments in, its figures to the file "out"
    a = json.loads(sys.argv[1])
    Path(a["out"]).write_text(json.dumps(load_once(Path(a["path"]), a["size"], a["backend"], a["threads"],
                                                   a["warm_workspace"])))
