"""Fuzzing bundle fields (the hardening issue's general property): whatever a bundle file holds, reading it either
gives an avatar that every backend renders, or raises the one typed error (BundleError naming a field); never
another exception. The mutations keep the content digest valid (the files are re-digested), so they reach the
structural checks, and each file is read both verified (an upload) and trusted (a load from the store, which
skips the digest and finiteness pass).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from test_bundle import _read_raw, _write_raw

from render_core.bundle import read_bundle, write_bundle
from render_core.camera import orbit
from render_core.deform import Frame
from render_core.errors import BlendsplatError, BundleError
from render_core.raster import native
from render_core.renderer import AvatarRenderer
from render_core.tools.synth import synth_avatar

CASES = 400
BACKENDS = ["reference"] + (["native"] if native.available() else [])


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz") / "base.bundle"
    write_bundle(synth_avatar(gaussians=120, blendshapes=4, seed=2, mouth=16, local=True), path)
    return _read_raw(path)


def _junk(rng: np.random.Generator):
    return rng.choice(np.array([0, -1, 1, 3, 2**31, -(2**40), 1e30, "x", None, [], {}, [1, 2], True], dtype=object))


def _mutate_values(t: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    a = t.numpy().copy()
    flat = a.reshape(-1)
    if flat.size == 0:
        return t
    idx = rng.integers(0, flat.size, size=int(rng.integers(1, 4)))
    if np.issubdtype(a.dtype, np.floating):
        flat[idx] = rng.choice([np.nan, np.inf, -np.inf, 1e4, -1e4, 0.0])
    else:
        info = np.iinfo(a.dtype)
        choices = [info.min, info.max, 0, int(flat.max()) + 1, flat.size, max(info.min, -1)]
        flat[idx] = np.array(rng.choice(choices), dtype=np.int64).astype(a.dtype)
    return torch.from_numpy(a)


def _mutate(tensors: dict, manifest: dict, rng: np.random.Generator) -> tuple[dict, dict, str]:
    tensors, manifest = dict(tensors), copy.deepcopy(manifest)
    name = rng.choice(sorted(tensors))
    kind = rng.choice(["values", "values", "shape", "dtype", "manifest", "drop"])
    t = tensors[name]
    if kind == "values":
        tensors[name] = _mutate_values(t, rng)
    elif kind == "shape" and t.dim() > 0:
        n = t.shape[0]
        tensors[name] = t[: int(rng.integers(0, n))] if n and rng.random() < 0.5 else torch.cat([t, t[:1]])
    elif kind == "dtype":
        tensors[name] = t.to(rng.choice([torch.float32, torch.float16, torch.int32, torch.int16, torch.uint8]))
    elif kind == "drop":
        del tensors[name]
    else:
        target, key = manifest, None
        for _ in range(3):  # walk a little into nested objects
            keys = [k for k in target if k not in ("tensors", "digest")] if isinstance(target, dict) else []
            if not keys:
                break
            key = rng.choice(sorted(keys))
            if not isinstance(target[key], dict) or rng.random() < 0.5:
                break
            target = target[key]
        if key is not None:
            target[key] = _junk(rng)
        name = f"manifest.{key}"
    return tensors, manifest, f"{kind} {name}"


def _render(avatar, backend: str) -> None:
    frame = Frame.neutral(avatar)
    AvatarRenderer(avatar, backend).render(frame, orbit(0.0, width=32, height=32))


def test_fuzzed_bundles_render_or_raise_the_typed_error(base, tmp_path):
    tensors, manifest = base
    rng = np.random.default_rng(1234)
    outcomes = {"refused": 0, "rendered": 0}
    for case in range(CASES):
        mutated, m, what = _mutate(tensors, manifest, rng)
        path = tmp_path / f"{case}.bundle"
        try:
            _write_raw(path, mutated, m)
        except (KeyError, TypeError, ValueError, OverflowError):
            continue  # the mutation is not even writable as safetensors
        for verify in (True, False):
            try:
                avatar = read_bundle(path, verify=verify)
            except BundleError as e:
                assert e.field, f"case {case} ({what}): a BundleError without a field: {e}"
                outcomes["refused"] += 1
                continue
            except Exception as e:  # noqa: BLE001 - the property under test
                pytest.fail(f"case {case} ({what}, verify={verify}): {type(e).__name__}: {e}")
            for backend in BACKENDS:
                try:
                    _render(avatar, backend)
                    outcomes["rendered"] += 1
                except BlendsplatError:
                    outcomes["refused"] += 1  # typed (e.g. a trusted load of non-finite values)
                except Exception as e:  # noqa: BLE001 - the property under test
                    pytest.fail(f"case {case} ({what}, verify={verify}, {backend}): {type(e).__name__}: {e}")

    assert outcomes["refused"] > CASES // 2 and outcomes["rendered"] > 0, outcomes  # both paths exercised


def test_fuzzed_bundle_uploads_never_get_a_server_error_and_the_demo_keeps_rendering(base, tmp_path, live_server):
    import httpx

    tensors, manifest = base
    rng = np.random.default_rng(99)
    codes = []
    with httpx.Client(base_url=live_server.http_url, timeout=60) as http:
        for case in range(30):
            mutated, m, what = _mutate(tensors, manifest, rng)
            path = tmp_path / f"up{case}.bundle"
            try:
                _write_raw(path, mutated, m)
            except (KeyError, TypeError, ValueError, OverflowError):
                continue
            r = http.put(f"/v1/avatars/fuzz-{case}", content=path.read_bytes())
            codes.append(r.status_code)
            assert r.status_code in (201, 422), (case, what, r.status_code, r.text)
            if r.status_code == 201:
                shown = http.post("/v1/render", json={"avatarId": f"fuzz-{case}", "width": 32, "height": 32})
                assert shown.status_code < 500, (case, what, shown.text)
                http.delete(f"/v1/avatars/fuzz-{case}")
        assert http.post("/v1/render", json={"avatarId": "demo", "width": 32, "height": 32}).status_code == 200
    assert 422 in codes and 201 in codes, codes
