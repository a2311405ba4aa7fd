"""The API contract (issue 17) on the real servers: the OpenAPI document is exact enough to generate a client from,
errors have one shape, and the streams end the way the proto says."""

from __future__ import annotations

import grpc
import httpx
import pytest
from conftest import LiveServer
from grpc_reflection.v1alpha import reflection_pb2
from test_service import _metric as metric
from websockets.sync.client import connect

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from service.access.http import OPEN_PATHS


@pytest.fixture(scope="module")
def keyed(tmp_path_factory):
    """A server with keys (the default) and the training routes, as `serve` runs it."""
    server = LiveServer(tmp_path_factory.mktemp("contract"), auth="keys")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def spec(keyed) -> dict:
    r = httpx.get(keyed.http_url + "/openapi.json", timeout=30)
    assert r.status_code == 200
    return r.json()


def operations(spec):
    for path, methods in spec["paths"].items():
        for method, operation in methods.items():
            yield path, method, operation


def test_every_operation_documents_its_error_statuses_with_the_one_error_model(spec):
    assert "HTTPValidationError" not in str(spec)  # FastAPI's {"detail": [...]} is never what answers
    error_ref = "#/components/schemas/ErrorBody"
    assert {"code", "message", "field"} <= set(spec["components"]["schemas"]["ErrorDetail"]["properties"])
    checked = 0
    for path, method, operation in operations(spec):
        responses = operation["responses"]
        expected = {"500", "503"} | ({"401", "403", "404", "422", "429"} if path not in OPEN_PATHS else set())
        assert expected <= set(responses), (method, path, sorted(responses))
        for status in expected - ({"503"} if path == "/readyz" else set()):  # readiness answers its reasons
            assert responses[status]["content"]["application/json"]["schema"]["$ref"] == error_ref
        if path not in OPEN_PATHS:
            assert operation.get("security"), (method, path)  # the bearer scheme is on it
            checked += 1
    assert checked >= 15
    assert spec["components"]["securitySchemes"]["apiKey"]["scheme"].lower() == "bearer"


def test_path_parameters_have_patterns_and_bodies_have_schemas(spec):
    for path, method, operation in operations(spec):
        for parameter in operation.get("parameters", []):
            if parameter["in"] == "path":
                schema = parameter["schema"]
                assert "pattern" in schema or "enum" in schema or "anyOf" in schema or path.startswith(
                    "/v1/adapters"), (method, path, parameter)
        if method in ("put", "post") and path in ("/v1/render", "/v1/jobs", "/v1/uploads", "/v1/avatars/{avatar_id}",
                                                  "/v1/adapters/{adapter_id}"):
            assert operation["requestBody"]["content"], (method, path)
    render = spec["paths"]["/v1/render"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    assert render["required"] == ["avatar_id"] and render["properties"]["width"]["maximum"] == 2048
    adapter = spec["paths"]["/v1/adapters/{adapter_id}"]["put"]["requestBody"]["content"]["multipart/form-data"]
    assert adapter["schema"]["required"] == ["manifest", "model"]


def test_every_success_answer_is_typed_and_created_resources_link_to_their_operations(spec):
    for path, method, operation in operations(spec):
        for status, response in operation["responses"].items():
            if status.startswith("2") and status != "204":
                content = response.get("content")
                assert content and all(media.get("schema") for media in content.values()), (method, path, status)
                for media in content.values():
                    schema = media["schema"]
                    assert schema != {} and schema.get("additionalProperties") is not True, (method, path, status)
    for path, method, status, target in (("/v1/uploads", "post", "201", "/v1/uploads/{upload_id}"),
                                         ("/v1/jobs", "post", "201", "/v1/jobs/{job_id}/events"),
                                         ("/v1/avatars/{avatar_id}", "put", "201", "/v1/avatars/{avatar_id}"),
                                         ("/v1/adapters/{adapter_id}", "put", "201", "/v1/adapters/{adapter_id}")):
        links = spec["paths"][path][method]["responses"][status]["links"]
        refs = {link["operationRef"] for link in links.values()}
        assert any(ref.startswith("#/paths/" + target.replace("/", "~1") + "/") for ref in refs), (path, refs)


def test_render_bodies_take_proto_field_names_and_protobufs_json_names(live_server):
    for body in ({"avatar_id": "demo", "width": 32, "frame": {"named_coefficients": {}, "client_time_us": 5}},
                 {"avatarId": "demo", "width": 32, "frame": {"namedCoefficients": {}, "clientTimeUs": "5"}}):
        r = httpx.post(live_server.http_url + "/v1/render", json=body, timeout=60)
        assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg", r.text


@pytest.mark.parametrize("demo", ["trained", "synthetic", "open-head"])
def test_the_render_example_works_against_every_demo_avatar(tmp_path, spec, demo):
    example = spec["paths"]["/v1/render"]["post"]["requestBody"]["content"]["application/json"]["schema"][
        "examples"][0]
    server = LiveServer(tmp_path / "data", demo_avatar=demo, demo_gaussians=2000)
    try:
        r = httpx.post(server.http_url + "/v1/render", json=example, timeout=60)
        assert r.status_code == 200 and r.headers["content-type"] == "image/png", r.text
    finally:
        server.stop()


def test_errors_have_one_shape_including_405_with_the_whole_allow_header(keyed):
    with httpx.Client(base_url=keyed.http_url, headers=keyed.headers, timeout=30) as http:
        r = http.post("/v1/avatars/demo")
        assert r.status_code == 405
        assert set(r.headers["allow"].replace(" ", "").split(",")) >= {"GET", "PUT", "DELETE"}
        assert r.json()["error"]["code"] == "INVALID_ARGUMENT" and "PUT" in r.json()["error"]["message"]
        r = http.post("/v1/jobs", content=b"\xff{", headers={"Content-Type": "application/json"})
        assert r.status_code == 422 and r.json()["error"]["field"] == "body"
        r = http.get("/v1/avatars/no-such-avatar")
        assert r.status_code == 404 and set(r.json()["error"]) == {"code", "message", "field"}
        r = http.get("/v1/avatars/bad%20id")
        assert r.status_code == 422 and r.json()["error"]["field"] == "avatar_id"


def test_docs_are_served_without_a_cdn(keyed):
    page = httpx.get(keyed.http_url + "/docs", timeout=30)
    assert page.status_code == 200 and "cdn" not in page.text.lower() and "/static/swagger/" in page.text
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css"):
        assert httpx.get(f"{keyed.http_url}/static/swagger/{asset}", timeout=30).status_code == 200


def test_a_websocket_end_message_is_answered_by_the_final_status(keyed):
    protocols = ["blendsplat.v1", f"bearer.{keyed.api_key}"]
    with connect(keyed.ws_url, subprotocols=protocols, open_timeout=30) as ws:
        ws.send(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=32, height=32)).SerializeToString())
        assert pb.StreamResponse.FromString(ws.recv(timeout=30)).HasField("header")
        ws.send(pb.StreamRequest(frame=pb.FrameParams(index=1)).SerializeToString())
        assert pb.StreamResponse.FromString(ws.recv(timeout=30)).frame.index == 1
        ws.send(pb.StreamRequest(end=pb.End()).SerializeToString())
        final = pb.StreamResponse.FromString(ws.recv(timeout=30))
    assert final.HasField("status") and final.status.code == pb.OK and final.status.frames_sent == 1


def test_grpc_reflection_is_served_as_v1_and_v1alpha(keyed):
    with grpc.insecure_channel(keyed.grpc_target) as channel:
        for name in ("grpc.reflection.v1.ServerReflection", "grpc.reflection.v1alpha.ServerReflection"):
            call = channel.stream_stream(f"/{name}/ServerReflectionInfo",
                                         request_serializer=reflection_pb2.ServerReflectionRequest.SerializeToString,
                                         response_deserializer=reflection_pb2.ServerReflectionResponse.FromString)
            replies = list(call(iter([reflection_pb2.ServerReflectionRequest(list_services="")]), timeout=30))
            names = {s.name for s in replies[0].list_services_response.service}
            assert "blendsplat.v1.RenderService" in names, (name, names)


def _metric(http: httpx.Client, name: str, **labels) -> float:
    return metric(http.get("/metrics").text, name, ",".join(f'{k}="{v}"' for k, v in labels.items()))


def test_metrics_count_errors_by_code_and_transport_and_misses_only_for_loads(keyed):
    with httpx.Client(base_url=keyed.http_url, headers=keyed.headers, timeout=30) as http:
        http_404 = _metric(http, "blendsplat_errors_total", code="NOT_FOUND", transport="http")
        grpc_404 = _metric(http, "blendsplat_errors_total", code="NOT_FOUND", transport="grpc")
        ws_401 = _metric(http, "blendsplat_errors_total", code="UNAUTHENTICATED", transport="websocket")
        misses = _metric(http, "blendsplat_avatar_cache_misses_total")
        assert http.get("/v1/avatars/missing").status_code == 404
        with grpc.insecure_channel(keyed.grpc_target) as channel, pytest.raises(grpc.RpcError):
            opened = pb.StreamRequest(open=pb.SessionConfig(avatar_id="missing", width=16, height=16))
            list(pb_grpc.RenderServiceStub(channel).RenderStream(
                iter([opened]), metadata=(("authorization", f"Bearer {keyed.api_key}"),)))
        with connect(keyed.ws_url, subprotocols=["blendsplat.v1"], open_timeout=30) as ws:  # no key
            ws.send(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo")).SerializeToString())
            assert pb.StreamResponse.FromString(ws.recv(timeout=30)).status.code == pb.UNAUTHENTICATED
        assert _metric(http, "blendsplat_errors_total", code="NOT_FOUND", transport="http") == http_404 + 1
        assert _metric(http, "blendsplat_errors_total", code="NOT_FOUND", transport="grpc") == grpc_404 + 1
        assert _metric(http, "blendsplat_errors_total", code="UNAUTHENTICATED", transport="websocket") == ws_401 + 1
        assert _metric(http, "blendsplat_avatar_cache_misses_total") == misses  # a missing avatar loads nothing
        assert "blendsplat_frame_bytes_total" in http.get("/metrics").text


def test_a_failed_open_gives_the_same_status_on_both_transports(keyed):
    """gRPC: the call's code, plus the whole Status in the trailer blendsplat-status-bin; WebSocket: the Status
    message, then the close."""
    opened = pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=16, height=16, max_in_flight=99))
    with grpc.insecure_channel(keyed.grpc_target) as channel, pytest.raises(grpc.RpcError) as caught:
        list(pb_grpc.RenderServiceStub(channel).RenderStream(
            iter([opened]), metadata=(("authorization", f"Bearer {keyed.api_key}"),)))
    trailer = dict(caught.value.trailing_metadata())["blendsplat-status-bin"]
    over_grpc = pb.Status.FromString(trailer)
    with connect(keyed.ws_url, subprotocols=["blendsplat.v1", f"bearer.{keyed.api_key}"], open_timeout=30) as ws:
        ws.send(opened.SerializeToString())
        over_ws = pb.StreamResponse.FromString(ws.recv(timeout=30)).status
    assert over_grpc == over_ws and over_ws.code == pb.INVALID_ARGUMENT and over_ws.field == "max_in_flight"
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_schemathesis_with_every_check_finds_nothing(keyed, tmp_path):
    """Schemathesis 4 on /openapi.json, every check on, with the admin key and the repository's schemathesis.toml
    (its one entry: the three file uploads may answer 422 to schema-valid bytes that are not such a file)."""
    import subprocess
    import sys
    from pathlib import Path

    tool = Path(sys.executable).parent / "schemathesis"
    if not tool.exists():
        pytest.skip("schemathesis is not installed (it is in the dev extra)")
    config = Path(__file__).parents[1] / "schemathesis.toml"
    result = subprocess.run(
        [str(tool), "--config-file", str(config), "run", f"{keyed.http_url}/openapi.json", "--checks", "all",
         "--max-examples", "15", "--seed", "1", "-H", f"Authorization: Bearer {keyed.api_key}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
