"""The trained demo avatar the package ships (render_core/facemodel/demo-avatar.bsplat): a valid, compact, trained
bundle on the open head that `blendsplat bundle build-demo` rebuilds, and the service's default demo, copied into an
empty store in well under a second and shown as trained (with its held-out psnr_head) over REST and gRPC."""

from __future__ import annotations

import inspect
import math
import time
from types import SimpleNamespace

import grpc
import httpx
import pytest

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.bundle import read_bundle_and_manifest, read_manifest, stored_schema_version, validate_bundle
from render_core.errors import OptionError
from render_core.facemodel.open_head import DEMO_AVATAR
from render_core.tools.cli import build_parser
from render_core.tools.demo import DEMO_RECIPE, MAX_DEMO_BYTES, _publish, build_demo_avatar
from render_core.train.initialize import init_avatar


@pytest.fixture(scope="module")
def shipped() -> dict:
    return validate_bundle(DEMO_AVATAR)  # digest, shapes, finite values


# ------------------------------------------------------------------------------------------- the shipped file
def test_the_shipped_demo_avatar_is_a_compact_trained_bundle_on_the_open_head(shipped, head):
    m = shipped
    assert DEMO_AVATAR.stat().st_size <= MAX_DEMO_BYTES == 16 << 20
    assert stored_schema_version(DEMO_AVATAR) == m["schema_version"] == 2 and m["precision"] == "fp16"
    # the pipeline's output in kind: what `blendsplat train` writes from a dataset on the open head
    init = init_avatar(head, gaussians=64, mouth=8, seed=0)
    assert m["face_model"] == head.name and m["expression_names"] == list(head.expression_names)
    assert m["joint_names"] == list(init.joint_names) and m["joint_parents"] == [int(p) for p in init.joint_parents]
    assert m["mouth_joint_names"] == list(init.mouth_joint_names) and m["sh_degree"] == init.sh_degree
    assert m["counts"]["blendshapes"] == head.num_expressions and m["counts"]["gaussians"] >= DEMO_RECIPE["gaussians"]
    p = m["provenance"]
    assert p["generator"] == "blendsplat train"
    t = p["trained"]
    assert {k: t[k] for k in ("iterations", "preset", "seed", "consistency")} == {
        "iterations": DEMO_RECIPE["iterations"], "preset": DEMO_RECIPE["preset"], "seed": DEMO_RECIPE["seed"],
        "consistency": "all"}
    held_out = t["held_out"]
    assert held_out["split"] == "test" and held_out["frames"] > 0 and held_out["psnr_head"] >= 30.0
    ds = t["dataset"]
    assert ds["synthetic"] == {"generator": "blendsplat data synth", "frames": DEMO_RECIPE["frames"],
                               "size": DEMO_RECIPE["size"], "seed": DEMO_RECIPE["data_seed"], "face_model": head.name}
    assert (ds["frames"], ds["width"], ds["height"]) == (DEMO_RECIPE["frames"], DEMO_RECIPE["size"],
                                                         DEMO_RECIPE["size"])
    assert ds["test"] == held_out["frames"] and ds["digest"].startswith("sha256:")
    assert p["recipe"] == {"command": "blendsplat bundle build-demo", **DEMO_RECIPE}


def test_the_build_command_defaults_are_the_recorded_recipe():
    args = build_parser().parse_args(["bundle", "build-demo", "--out", "x.bsplat"])
    assert {k: getattr(args, k) for k in DEMO_RECIPE} == DEMO_RECIPE
    defaults = inspect.signature(build_demo_avatar).parameters
    assert {k: defaults[k].default for k in DEMO_RECIPE} == DEMO_RECIPE


def test_the_builder_runs_the_pipeline_and_an_identical_rebuild_leaves_the_file_alone(tmp_path, head):
    """A tiny run of the same builder (the shipped file's takes minutes): synthetic video -> training -> a compact
    bundle whose provenance records the recipe; then the publishing step on the same content keeps the file."""
    out = tmp_path / "demo.bsplat"
    r = build_demo_avatar(out, frames=12, size=48, iterations=6, gaussians=400, min_psnr_head=-math.inf,
                          workdir=tmp_path / "work")
    m = validate_bundle(out)
    assert r["bytes"] == out.stat().st_size and r["digest"] == m["digest"] and not r["unchanged"]
    assert m["schema_version"] == 2 and m["precision"] == "fp16" and m["expression_names"] == list(
        head.expression_names)
    assert m["provenance"]["trained"]["held_out"]["psnr_head"] == r["psnr_head"]
    assert m["provenance"]["recipe"]["gaussians"] == 400 and m["provenance"]["recipe"]["threads"] == 2
    assert m["provenance"]["trained"]["dataset"]["synthetic"]["size"] == 48

    avatar, manifest = read_bundle_and_manifest(out)
    before = out.stat().st_mtime_ns, out.read_bytes()
    provenance = {k: v for k, v in manifest["provenance"].items() if k != "created_at"}
    time.sleep(1.1)  # a new creation time would differ
    kept, unchanged = _publish(avatar, provenance, out, MAX_DEMO_BYTES)
    assert unchanged and kept["digest"] == manifest["digest"]
    assert (out.stat().st_mtime_ns, out.read_bytes()) == before
    # new content gets a new file (and a new creation time); one over the size limit is refused, the old file kept
    changed, unchanged = _publish(avatar, {**provenance, "note": "changed"}, out, MAX_DEMO_BYTES)
    assert not unchanged and changed["digest"] != manifest["digest"]
    assert read_manifest(out)["provenance"]["created_at"] != manifest["provenance"]["created_at"]
    with pytest.raises(OptionError, match="fewer --gaussians"):
        _publish(avatar, {**provenance, "note": "too big"}, out, 1000)
    assert read_manifest(out)["digest"] == changed["digest"]


# ----------------------------------------------------------------------------------------------- the service
def test_the_default_demo_is_the_shipped_one_copied_validated_in_well_under_a_second(tmp_path):
    from service.server import DEMO_ID, DEMO_OWNER, make_demo_avatar
    from service.settings import Settings
    from service.store import BundleStore

    settings = Settings(data_dir=tmp_path)
    assert settings.demo_avatar == "trained"  # the default
    store = BundleStore(settings.bundle_dir)
    store.ensure()
    t0 = time.perf_counter()
    what = make_demo_avatar(settings, SimpleNamespace(store=store))
    assert time.perf_counter() - t0 < 1.0
    assert "trained" in what and "psnr_head" in what
    assert store.path(DEMO_ID).read_bytes() == DEMO_AVATAR.read_bytes()
    assert store.owner(DEMO_ID) == DEMO_OWNER and store.sidecars(DEMO_ID)[0].is_file()  # public, verified


def test_without_the_shipped_file_the_demo_is_the_open_head(tmp_path, monkeypatch):
    from service import demo as server
    from service.settings import Settings
    from service.store import BundleStore

    monkeypatch.setattr(server, "DEMO_AVATAR", tmp_path / "missing.bsplat")
    settings = Settings(data_dir=tmp_path / "data", demo_gaussians=320)
    store = BundleStore(settings.bundle_dir)
    store.ensure()
    assert "untrained" in server.make_demo_avatar(settings, SimpleNamespace(store=store))
    m = validate_bundle(store.path(server.DEMO_ID))
    assert m["counts"]["gaussians"] + m["counts"]["mouth"] == 320 and "trained" not in m["provenance"]


def test_a_fresh_server_is_ready_quickly_and_shows_the_demo_trained(tmp_path):
    from conftest import LiveServer

    from service.settings import Settings

    t0 = time.perf_counter()
    server = LiveServer(tmp_path / "data", demo_avatar=Settings().demo_avatar)  # the default: trained
    try:
        assert time.perf_counter() - t0 < 20
        shipped = read_manifest(DEMO_AVATAR)
        psnr_head = shipped["provenance"]["trained"]["held_out"]["psnr_head"]
        r = httpx.get(server.http_url + "/v1/avatars/demo", timeout=30)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["trained"] is True and body["psnr_head"] == pytest.approx(psnr_head) and body["psnr_head"] >= 30
        assert body["file_bytes"] == DEMO_AVATAR.stat().st_size and body["digest"] == shipped["digest"]
        assert body["precision"] == "fp16" and "jawOpen" in body["expression_names"]
        with grpc.insecure_channel(server.grpc_target) as channel:
            stub = pb_grpc.RenderServiceStub(channel)
            info = stub.GetAvatar(pb.GetAvatarRequest(id="demo"), timeout=30)
            assert info.trained and info.HasField("psnr_head") and info.psnr_head == pytest.approx(psnr_head)
            listed = {a.id: a for a in stub.ListAvatars(pb.ListAvatarsRequest(), timeout=30).avatars}
            assert listed["demo"].trained and listed["demo"].psnr_head == pytest.approx(psnr_head)
        loaded = httpx.post(server.http_url + "/v1/avatars/demo/load", timeout=60).json()  # from the cache's copy
        assert loaded["loaded"] and loaded["trained"] is True and loaded["psnr_head"] == pytest.approx(psnr_head)
    finally:
        server.stop()


def test_an_untrained_avatar_shows_trained_false_and_no_psnr_head(live_server):
    body = httpx.get(live_server.http_url + "/v1/avatars/demo", timeout=30).json()  # the synthetic demo
    assert body["trained"] is False and body["psnr_head"] is None
    with grpc.insecure_channel(live_server.grpc_target) as channel:
        info = pb_grpc.RenderServiceStub(channel).GetAvatar(pb.GetAvatarRequest(id="demo"), timeout=30)
    assert not info.trained and not info.HasField("psnr_head")
