"""Adapters made from capture vocabularies with nothing but the install (`blendsplat adapter make`): MediaPipe's 52
face blendshapes and Live Link Face's columns onto the open head, their known answers (one-hot inputs), and a
MediaPipe stream driving an open-head avatar through the service after an upload with the admin key."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from render_core.adapters.onnx_model import model_bytes
from render_core.adapters.runtime import AdapterRuntime
from render_core.adapters.validate import validate_model
from render_core.adapters.vocabularies import (
    LIVE_LINK_FACE,
    MEDIAPIPE_52,
    VOCABULARIES,
    arkit_matrix,
    make_adapter,
    vocabulary,
)
from render_core.facemodel.open_head import ARKIT_52

# MediaPipe FaceLandmarker's face blendshape categories, index 0 to 51, as its documentation lists them.
MEDIAPIPE_DOCUMENTED = """
_neutral browDownLeft browDownRight browInnerUp browOuterUpLeft browOuterUpRight cheekPuff cheekSquintLeft
cheekSquintRight eyeBlinkLeft eyeBlinkRight eyeLookDownLeft eyeLookDownRight eyeLookInLeft eyeLookInRight
eyeLookOutLeft eyeLookOutRight eyeLookUpLeft eyeLookUpRight eyeSquintLeft eyeSquintRight eyeWideLeft eyeWideRight
jawForward jawLeft jawOpen jawRight mouthClose mouthDimpleLeft mouthDimpleRight mouthFrownLeft mouthFrownRight
mouthFunnel mouthLeft mouthLowerDownLeft mouthLowerDownRight mouthPressLeft mouthPressRight mouthPucker mouthRight
mouthRollLower mouthRollUpper mouthShrugLower mouthShrugUpper mouthSmileLeft mouthSmileRight mouthStretchLeft
mouthStretchRight mouthUpperUpLeft mouthUpperUpRight noseSneerLeft noseSneerRight
""".split()


def _run(fit, source: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    data = model_bytes(fit.manifest, fit.weights, fit.bias)
    expression, joints, errors = AdapterRuntime(data, fit.manifest).run(np.asarray(source, np.float32))
    assert all(e is None for e in errors)
    return expression, joints


def test_mediapipe_vocabulary_is_mediapipes_order_and_maps_onto_the_open_head():
    assert MEDIAPIPE_52 == MEDIAPIPE_DOCUMENTED and len(MEDIAPIPE_52) == 52
    assert set(MEDIAPIPE_52) == set(ARKIT_52) - {"tongueOut"} | {"_neutral"}
    v = vocabulary("mediapipe")
    assert list(v.names) == MEDIAPIPE_52 and v.convention == "mediapipe-52"
    assert v.mapping()["_neutral"] is None
    assert all(v.mapping()[n] == n for n in MEDIAPIPE_52[1:])
    assert v.to_dict()["open_head_names_not_driven"] == ["tongueOut"]
    assert MEDIAPIPE_52.index("jawOpen") == 25 and MEDIAPIPE_52.index("eyeBlinkLeft") == 9


def test_live_link_face_vocabulary():
    v = vocabulary("live-link-face")
    assert len(v.names) == 61 and list(v.names) == LIVE_LINK_FACE
    assert v.names[:3] == ("EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft")
    assert v.names[14:18] == ("JawForward", "JawLeft", "JawRight", "JawOpen") and v.names[51] == "TongueOut"
    assert v.names[52:55] == ("HeadYaw", "HeadPitch", "HeadRoll")
    m = v.mapping()
    assert {m[n] for n in v.names[:52]} == set(ARKIT_52) and m["MouthSmileLeft"] == "mouthSmileLeft"
    assert all(m[n] is None for n in v.names[52:])
    with pytest.raises(Exception, match="no vocabulary") as e:
        vocabulary("openface")
    assert e.value.field == "source"


@pytest.mark.parametrize("name", list(VOCABULARIES))
def test_made_adapter_is_valid_and_each_name_drives_its_expression(name, head):
    """Known answer: one-hot inputs, one per source name, give the one-hot of that name's open-head expression
    (nothing for _neutral and the rotations); outputs are clamped to [0, 1]."""
    v = vocabulary(name)
    fit = make_adapter(name)
    m = fit.manifest
    assert m.id == f"{name}-to-open-head" and m.target_face_model == head.name
    assert m.source_names == list(v.names) and m.target_expression_names == head.expression_names
    assert m.source_convention == v.convention and m.target_joint_names == []
    validate_model(model_bytes(m, fit.weights, fit.bias), m)
    expression, joints = _run(fit, np.eye(len(v.names)))
    assert joints.shape == (len(v.names), 0, 3)
    for i, source in enumerate(v.names):
        want = np.zeros(52)
        if v.maps_to[i] is not None:
            want[head.expression_names.index(v.maps_to[i])] = 1.0
        np.testing.assert_array_equal(expression[i], want, err_msg=source)
    expression, _ = _run(fit, np.full((1, len(v.names)), 3.0))
    np.testing.assert_array_equal(expression[0], arkit_matrix(v).any(1).astype(float))  # clamped to 1; undriven: 0
    expression, _ = _run(fit, np.full((1, len(v.names)), -2.0))
    assert (expression == 0).all()


def test_neutral_has_no_effect(head):
    fit = make_adapter("mediapipe")
    x = np.random.default_rng(0).uniform(0, 1, (4, 52))
    with_neutral = x.copy()
    with_neutral[:, 0] = [0.0, 0.3, 1.0, 7.0]
    a, _ = _run(fit, x)
    b, _ = _run(fit, with_neutral)
    np.testing.assert_array_equal(a, b)
    # the rest is the same coefficients by name, in the open head's order
    np.testing.assert_allclose(a[:, [head.expression_names.index(n) for n in MEDIAPIPE_52[1:]]], x[:, 1:], atol=1e-7)


def test_made_adapter_onto_another_face_model_composes_the_fit(head):
    """A target whose names are not ARKit's: the known mapping composed with the open head's least-squares fit."""
    from render_core.adapters.fit import fit as fit_models
    from tests.test_adapters import mixed

    target, _ = mixed(head, k=12)
    made = make_adapter("mediapipe", target)
    via = fit_models(head, target)
    assert made.manifest.id == "mediapipe-to-open-head-mixed" and made.manifest.source_names == MEDIAPIPE_52
    assert made.manifest.target_expression_names == target.expression_names
    np.testing.assert_allclose(made.weights, via.weights @ arkit_matrix(vocabulary("mediapipe")))
    x = np.zeros((1, 52))
    x[0, MEDIAPIPE_52.index("jawOpen")] = 0.5
    y = np.zeros((1, 52))
    y[0, ARKIT_52.index("jawOpen")] = 0.5
    np.testing.assert_allclose(made.apply(x)[0], via.apply(y)[0], atol=1e-12)


def test_adapter_make_command_writes_an_uploadable_adapter(tmp_path, capsys):
    from render_core.tools.cli import main

    out = tmp_path / "scratch"
    assert main(["adapter", "make", "--source", "mediapipe", "--target", "open-head", "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["id"] == "mediapipe-to-open-head" and report["source_names"] == MEDIAPIPE_52
    model, manifest = out / "mediapipe-to-open-head.onnx", out / "mediapipe-to-open-head.manifest.json"
    assert report["model"] == str(model) and report["manifest"] == str(manifest) and report["stored"] is None
    assert json.loads(manifest.read_text())["source"]["names"] == MEDIAPIPE_52
    assert main(["adapter", "validate", str(model), "--manifest", str(manifest)]) == 0
    assert json.loads(capsys.readouterr().out)["valid"] is True
    data = tmp_path / "data"
    assert main(["adapter", "make", "--source", "live-link-face", "--id", "llf", "--out", str(out),
                 "--data-dir", str(data)]) == 0
    capsys.readouterr()
    assert main(["adapter", "list", "--data-dir", str(data)]) == 0
    listed = json.loads(capsys.readouterr().out)["adapters"]
    assert [(a["id"], a["source_convention"], a["inputs"]) for a in listed] == [("llf", "live-link-face", 61)]
    assert main(["adapter", "vocabulary", "mediapipe"]) == 0
    assert json.loads(capsys.readouterr().out)["unmapped"] == ["_neutral"]
    assert main(["adapter", "make", "--source", "openface", "--out", str(out)]) == 1
    assert "no vocabulary" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------------ service
SIZE = 40
AVATAR = "open-head-avatar"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from tests.conftest import LiveServer

    s = LiveServer(tmp_path_factory.mktemp("vocabulary-server"), auth="keys", demo_avatar="open-head")
    yield s
    s.stop()


def test_service_accepts_the_made_adapter_and_mediapipe_streams_drive_the_avatar(server, head, tmp_path, capsys):
    """The README's path: make the adapter, PUT it with the admin key, open a stream that declares MediaPipe's
    names; the service picks the adapter, and each frame is the open-head avatar driven by the same coefficients
    by ARKit name (``_neutral`` changes nothing)."""
    import grpc
    import httpx

    from blendsplat.v1 import render_pb2 as pb
    from blendsplat.v1 import render_pb2_grpc as pb_grpc
    from render_core.bundle import read_bundle, write_bundle
    from render_core.deform import Frame
    from render_core.drive import default_camera
    from render_core.media.codecs import decode_image
    from render_core.renderer import AvatarRenderer
    from render_core.tools.cli import main
    from render_core.train.initialize import init_avatar
    from tests.test_adapters import _stripes
    from tests.test_service import GrpcStream, next_frame

    avatar = init_avatar(head, gaussians=1500, mouth=8, sh_degree=0, opacity=0.6, albedo=_stripes, seed=0)
    write_bundle(avatar, tmp_path / "a.bundle", precision="fp32")
    assert main(["adapter", "make", "--source", "mediapipe", "--out", str(tmp_path)]) == 0
    adapter_id = json.loads(capsys.readouterr().out)["id"]
    with httpx.Client(base_url=server.http_url, headers=server.headers, timeout=120) as http:
        assert http.put(f"/v1/avatars/{AVATAR}", content=(tmp_path / "a.bundle").read_bytes()).status_code == 201
        files = {"manifest": ("m.json", (tmp_path / f"{adapter_id}.manifest.json").read_bytes(), "application/json"),
                 "model": ("a.onnx", (tmp_path / f"{adapter_id}.onnx").read_bytes(), "application/octet-stream")}
        r = http.put(f"/v1/adapters/{adapter_id}", files=files)
        assert r.status_code == 201, r.text
        assert r.json()["manifest"]["source"]["convention"] == "mediapipe-52"
    stored = read_bundle(server.engine.store.path(AVATAR))
    renderer = AvatarRenderer(stored)

    def expected(expression: dict[str, float]) -> np.ndarray:
        frame = Frame.from_params(stored, expression=expression)
        out = renderer.render(frame, default_camera(stored, SIZE, SIZE), torch.zeros(3))
        rgba = torch.cat([out.rgb[0], out.alpha[0, ..., None]], -1)
        return (rgba.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()

    rng = np.random.default_rng(3)
    mixed = rng.uniform(0, 1, 52) * (rng.uniform(size=52) < 0.3)
    frames = [  # (message fields, the same pose by the open head's names)
        (dict(coefficients=np.eye(52)[MEDIAPIPE_52.index("jawOpen")].tolist()), {"jawOpen": 1.0}),
        (dict(named_coefficients={"_neutral": 1.0, "eyeBlinkLeft": 0.7}), {"eyeBlinkLeft": 0.7}),
        (dict(coefficients=mixed.tolist()), {n: float(v) for n, v in zip(MEDIAPIPE_52, mixed, strict=True)
                                             if n != "_neutral"}),
    ]
    with grpc.insecure_channel(server.grpc_target) as channel:
        stream = GrpcStream(pb_grpc.RenderServiceStub(channel), api_key=server.api_key, avatar_id=AVATAR,
                            width=SIZE, height=SIZE, codec=pb.CODEC_PNG, source_names=MEDIAPIPE_52)
        header = stream.next().header
        assert header.adapter_id == adapter_id and list(header.source_names) == MEDIAPIPE_52
        assert list(header.expression_names) == ARKIT_52
        images = []
        for i, (fields, arkit) in enumerate(frames, start=1):
            stream.send(frame=pb.FrameParams(index=i, **fields))
            got = decode_image("png", next_frame(stream).data, SIZE, SIZE)
            assert np.abs(got.astype(int) - expected(arkit).astype(int)).max() <= 1, f"frame {i} differs"
            images.append(got)
            stream.send(ack=pb.Ack(index=i))
        assert np.abs(images[0].astype(int) - expected({}).astype(int)).max() > 10  # the jaw did open
        stream.send(frame=pb.FrameParams(index=4, named_coefficients={"tongueOut": 1.0}))  # not MediaPipe's
        assert stream.next().error.field == "named_coefficients"
        assert stream.close()[-1].status.code == pb.OK


def test_readme_mediapipe_example_runs_as_written(server, tmp_path, monkeypatch, capsys):
    """The README's adapter example, verbatim but for the addresses: the bash block (vocabulary, make, the curl
    upload with the admin key) and the Python stream that drives the demo avatar (on the open head) by
    MediaPipe's names, from a folder holding data/admin.key."""
    from render_core.media.codecs import decode_image

    section = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8").split(
        "## Retargeting adapters", 1)[1]
    bash = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "adapter make --source mediapipe" in bash and "source_names=MEDIAPIPE_52" in code
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "admin.key").write_text(server.api_key + "\n")
    monkeypatch.chdir(tmp_path)
    if shutil.which("curl") is None:
        pytest.skip("curl is not installed")
    blendsplat = str(Path(sys.executable).with_name("blendsplat"))
    script = bash.replace(".venv/bin/blendsplat", blendsplat).replace("http://127.0.0.1:8080", server.http_url)
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    stored = json.loads(done.stdout.strip().splitlines()[-1])  # the PUT's answer, curl's last line
    assert stored["id"] == "mediapipe-to-open-head" and stored["manifest"]["source"]["names"] == MEDIAPIPE_52
    exec(compile(code.replace("127.0.0.1:50051", server.grpc_target), "README.md:adapters", "exec"), {})  # noqa: S102
    assert "adapter: mediapipe-to-open-head" in capsys.readouterr().out
    image = decode_image("png", (tmp_path / "scratch" / "mediapipe.png").read_bytes(), 256, 256)
    assert image[..., 3].max() > 200  # the avatar is in the frame
