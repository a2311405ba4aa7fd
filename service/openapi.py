"""The HTTP API's description (``/openapi.json``) made exact: the one error model, and every status each route can
answer, added to every operation from what the route is (protected, with path parameters, with a body).

FastAPI documents what a route declares; the answers every route shares (a missing or wrong key, a draining
server, a typed internal error, the body guard's 408/413) come from one place, :func:`document_errors`, so a new
route is documented like the others. ``tests/test_contract.py`` checks the result and runs schemathesis on it.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel, Field

CODES = ["INVALID_ARGUMENT", "NOT_FOUND", "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION",
         "INTERNAL", "UNAVAILABLE", "UNAUTHENTICATED", "CANCELLED"]


class ErrorDetail(BaseModel):
    code: str = Field(description="the status code's name (blendsplat.v1.Code), e.g. INVALID_ARGUMENT",
                      json_schema_extra={"enum": CODES})
    message: str = Field(description="what is wrong, for a person (bounded)")
    field: str = Field("", description="the request field at fault (its proto field path or the HTTP part: body, "
                                       "authorization, a parameter), or empty")
    errorId: str | None = Field(None, description="INTERNAL only: the id the server's log line has too")  # noqa: N815


class ErrorBody(BaseModel):
    """Every error answer: ``{"error": {"code", "message", "field"}}`` (service/errors.py)."""

    error: ErrorDetail


_WHY = {
    401: "no API key, or one that is unknown, revoked or malformed (WWW-Authenticate: Bearer)",
    403: "the key lacks the route's scope, or the resource belongs to another tenant",
    404: "no such resource",
    408: "the request body stalled (body_timeout_seconds)",
    409: "the resource's state does not allow it",
    413: "the request body is over its limit",
    422: "the request is not valid: the field at fault is named",
    429: "a limit: the key's streams, uploads or jobs per hour (Retry-After), the tenant's storage, the server's "
         "sessions or per-frame budget",
    500: "an internal error (an error id the log has too)",
    503: "the server is shutting down, or a store it needs is unreachable",
}


def _error(status: int) -> dict[str, Any]:
    response: dict[str, Any] = {"description": _WHY[status],
                                "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}}
    if status == 429:
        response["headers"] = {"Retry-After": {"description": "seconds to wait (per-key limits)",
                                               "schema": {"type": "integer"}}}
    if status == 401:
        response["headers"] = {"WWW-Authenticate": {"schema": {"type": "string"}}}
    return response


def render_request_schema(max_size: int, id_pattern: str) -> dict[str, Any]:
    """RenderRequest as JSON with its proto field names (snake_case; protobuf's camelCase JSON names are accepted
    too, as on the WebSocket): the fields a single-frame render reads (proto/blendsplat/v1/render.proto gives each
    one's meaning). Expression names are the avatar's own (GET /v1/avatars/{id}): unknown ones are refused
    with 422 naming them, as are poses and cameras that are not rotations and calibrations."""
    number = {"type": "number", "minimum": -3.0e38, "maximum": 3.0e38}  # a float32
    unit = {"type": "number", "minimum": 0, "maximum": 1}
    frame = {"type": "object", "additionalProperties": False, "properties": {
        "index": {"type": "integer", "minimum": 0, "maximum": 2**63 - 1, "description": "echoed back (0: unset)"},
        "client_time_us": {"type": "integer", "minimum": -(2**63), "maximum": 2**63 - 1,
                         "description": "the client's timestamp, echoed"},
        "named_coefficients": {"type": "object", "additionalProperties": number,
                              "description": "by the avatar's expression names (unknown names: 422)"},
        "eyelids": {"type": "array", "items": unit, "maxItems": 2, "description": "none, or [left, right]"},
        "background": {"type": "object", "additionalProperties": False,
                       "properties": {"r": unit, "g": unit, "b": unit}},
    }, "description": "FrameParams: also joints and camera (proto/blendsplat/v1/render.proto)"}
    return {"type": "object", "required": ["avatar_id"], "additionalProperties": False, "properties": {
        "avatar_id": {"type": "string", "pattern": id_pattern, "maxLength": 128},
        "width": {"type": "integer", "minimum": 0, "maximum": max_size,
                  "description": "0: the height (a square), or 512"},
        "height": {"type": "integer", "minimum": 0, "maximum": max_size,
                   "description": "0: the width (a square), or 512"},
        "codec": {"type": "string", "enum": ["CODEC_UNSPECIFIED", "CODEC_JPEG", "CODEC_PNG", "CODEC_RAW_RGBA"]},
        "quality": {"type": "integer", "minimum": 0, "maximum": 100, "description": "JPEG quality (0: default)"},
        "frame": frame,
        "reference": {"type": "boolean", "description": "render with every speed mechanism off (the same pixels, "
                                                        "slower): for checking them"},
    }, "examples": [{"avatar_id": "demo", "width": 256, "height": 256, "codec": "CODEC_PNG",
                     "frame": {"index": 1}}]}


# What a created resource's answer leads to (OpenAPI links: client generators and schemathesis' stateful phase
# follow them): (path, method, status) of the creating operation -> the operations its id addresses.
LINKS: dict[tuple[str, str, str], tuple[str, str, list[tuple[str, str]]]] = {
    ("/v1/uploads", "post", "201"): ("upload_id", "$response.body#/upload_id", [
        ("/v1/uploads/{upload_id}", "get"), ("/v1/uploads/{upload_id}", "delete")]),
    ("/v1/jobs", "post", "201"): ("job_id", "$response.body#/id", [
        ("/v1/jobs/{job_id}", "get"), ("/v1/jobs/{job_id}/events", "get"), ("/v1/jobs/{job_id}/cancel", "post"),
        ("/v1/jobs/{job_id}", "delete")]),
    ("/v1/avatars/{avatar_id}", "put", "201"): ("avatar_id", "$response.body#/id", [
        ("/v1/avatars/{avatar_id}", "get"), ("/v1/avatars/{avatar_id}/load", "post"),
        ("/v1/avatars/{avatar_id}/unload", "post"), ("/v1/avatars/{avatar_id}", "delete")]),
    ("/v1/adapters/{adapter_id}", "put", "201"): ("adapter_id", "$response.body#/id", [
        ("/v1/adapters/{adapter_id}", "get"), ("/v1/adapters/{adapter_id}", "delete")]),
}


def _add_links(paths: dict[str, Any]) -> None:
    for (path, method, status), (parameter, value, targets) in LINKS.items():
        response = paths.get(path, {}).get(method, {}).get("responses", {}).get(status)
        if response is None:
            continue
        response["links"] = {
            f"{target_method}{target.replace('/', '_').replace('{', '').replace('}', '')}": {
                "operationRef": "#/paths/" + target.replace("~", "~0").replace("/", "~1") + f"/{target_method}",
                "parameters": {parameter: value}}
            for target, target_method in targets if target_method in paths.get(target, {})}


def document_errors(app: FastAPI, open_paths: frozenset[str],
                    bodies: dict[tuple[str, str], dict[str, Any]] | None = None) -> None:
    """Make ``app.openapi()`` list every status each operation can answer, with the one error model; ``bodies``:
    request bodies of routes that read their body themselves, by (path, method)."""

    def build() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        body = ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")
        components.update(body.pop("$defs", {}))
        components["ErrorBody"] = body
        for name in ("HTTPValidationError", "ValidationError"):
            components.pop(name, None)
        for path, operations in schema.get("paths", {}).items():
            for method, operation in operations.items():
                if (path, method) in (bodies or {}):
                    operation["requestBody"] = bodies[(path, method)]
                responses = operation.setdefault("responses", {})
                statuses = {500, 503}
                if path not in open_paths:
                    statuses |= {401, 403, 429}
                if "{" in path or path not in open_paths:  # a path id, or an id in the body (avatar, upload)
                    statuses |= {404}
                if operation.get("parameters") or "requestBody" in operation or path not in open_paths:
                    statuses |= {422}
                if "requestBody" in operation or method in ("put", "post"):
                    statuses |= {408, 413, 409}
                for status in sorted(statuses):
                    responses.setdefault(str(status), _error(status))
                if "422" in responses and "HTTPValidationError" in str(responses["422"]):
                    responses["422"] = _error(422)
        _add_links(schema.get("paths", {}))
        app.openapi_schema = schema
        return schema

    app.openapi = build  # type: ignore[method-assign]
