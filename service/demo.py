"""The demo avatar ``demo`` put in an empty bundle store at start (``BLENDSPLAT_DEMO_AVATAR``): the trained one
shipped with the package (copied, verified), the untrained open head, a synthetic one, or none."""

from __future__ import annotations

import logging
import shutil

from render_core.atomic import atomic_path
from render_core.bundle import write_bundle
from render_core.errors import BlendsplatError, FaceModelError
from render_core.facemodel.open_head import DEMO_AVATAR, open_head
from render_core.facemodel.synthetic import synth_avatar
from render_core.train.initialize import demo_albedo, init_avatar

from .access.auth import ADMIN_TENANT
from .engine import Engine
from .settings import Settings
from .store import Owner

log = logging.getLogger(__name__)

DEMO_ID = "demo"
DEMO_OWNER = Owner(ADMIN_TENANT, public=True)  # every key may read and stream the demo; only admin keys change it


def make_demo_avatar(settings: Settings, engine: Engine) -> str:
    """The demo avatar ``demo``, as ``demo_avatar`` asks; what it is, for the log.

    ``trained`` (the default): the package's trained demo avatar (render_core/facemodel/demo-avatar.bsplat, built
    by ``blendsplat bundle build-demo``), validated and copied into the store in well under a second; when it is
    missing or broken, the open head instead. ``open-head``: ``demo_gaussians`` Gaussians (15/16 face, 1/16
    mouth) in fp16 initialised on the open head model (K = 52 ARKit expressions, shipped with the package),
    untrained. ``synthetic``: a synthetic avatar of that size whose blendshapes have compact support."""
    if settings.demo_avatar == "trained":
        try:
            return _copy_trained_demo(engine)
        except (OSError, BlendsplatError) as e:
            log.warning("demo avatar: the shipped trained one cannot be used (%s); the open head instead", e)
    n = settings.demo_gaussians
    try:
        if settings.demo_avatar == "synthetic":
            raise FaceModelError("the settings ask for a synthetic demo avatar")
        model = open_head()
    except FaceModelError as e:
        log.warning("demo avatar: synthetic (%s)", e)
        avatar = synth_avatar(gaussians=n - n // 8, mouth=n // 8, blendshapes=settings.demo_blendshapes, seed=0,
                              local=True)
    else:
        avatar = init_avatar(model, gaussians=n - n // 16, mouth=n // 16, opacity=0.95, albedo=demo_albedo(model))
    write_bundle(avatar, engine.store.path(DEMO_ID), precision="fp16")
    engine.store.adopt(DEMO_ID)  # verified once, here: later loads trust the store's record
    engine.store.set_owner(DEMO_ID, DEMO_OWNER)
    return f"{n} Gaussians, {avatar.face_model}, untrained"


def _copy_trained_demo(engine: Engine) -> str:
    """Copy the shipped trained demo avatar into the store as ``demo``: fully verified once (the store's record
    then spares later loads the digest), public, owned by admin; what it is, for the log."""
    path = engine.store.path(DEMO_ID)
    with atomic_path(path) as tmp:
        shutil.copyfile(DEMO_AVATAR, tmp)
    try:
        manifest = engine.store.adopt(DEMO_ID)  # fully verified (before the servers start), recorded as verified
    except BaseException:
        path.unlink(missing_ok=True)  # a broken copy never stays in the store
        raise
    engine.store.set_owner(DEMO_ID, DEMO_OWNER)
    c, trained = manifest["counts"], manifest["provenance"].get("trained", {})
    psnr_head = (trained.get("held_out") or {}).get("psnr_head")
    return (f"{c['gaussians'] + c['mouth']} Gaussians, {manifest['face_model']}, trained "
            f"({trained.get('iterations')} iterations, held-out psnr_head {psnr_head} dB)")
