"""The data channel's requests: ``StreamRequest`` as protobuf JSON (text) or protobuf (binary).

A stream sends a pose 30 times a second or more, and the JSON parser of protobuf (``json_format``) walks each
message in Python: 0.1 ms a pose of the 52-expression avatars, on the event loop, for poses most of which a newer
one replaces before they render. :func:`parse` reads the plain pose, ``{"frame": {"index", "clientTimeUs",
"coefficients": [...], "joints": {NAME: {"values": [...]}}}}`` with camelCase names (what the Python and TypeScript
clients send), with :func:`json.loads` and builds the message directly; anything else (other fields or messages,
snake_case names, numbers as strings, non-finite or out-of-range numbers, duplicate keys) goes through
``json_format``, so every message parses to the same ``StreamRequest`` as before and every refusal is
``json_format``'s.
"""

from __future__ import annotations

import json
import math

from google.protobuf import json_format

from blendsplat.v1 import render_pb2 as pb

FLOAT_MAX = 3.4028234663852886e38  # the largest float32: json_format refuses more for a float field
POSE_KEYS = frozenset(("index", "clientTimeUs", "coefficients", "joints"))


class _Duplicate(Exception):
    """A JSON object with a key twice (json_format refuses it)."""


def _no_duplicates(pairs: list[tuple[str, object]]) -> dict:
    body = dict(pairs)
    if len(body) != len(pairs):
        raise _Duplicate
    return body


def _floats(values: object) -> bool:
    """A list of JSON numbers that json_format takes as they are for a float field."""
    return type(values) is list and all(
        (type(v) is float and math.isfinite(v) or type(v) is int) and -FLOAT_MAX <= v <= FLOAT_MAX for v in values)


def _plain_pose(text: str) -> pb.StreamRequest | None:
    """The request of a plain pose message, or None for anything else."""
    try:
        body = json.loads(text, object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError, _Duplicate):
        return None
    frame = body.get("frame") if type(body) is dict and len(body) == 1 else None
    if type(frame) is not dict or not frame.keys() <= POSE_KEYS:
        return None
    index, client_time = frame.get("index", 0), frame.get("clientTimeUs", 0)
    coefficients, joints = frame.get("coefficients", []), frame.get("joints", {})
    if (type(index) is not int or not 0 <= index < 1 << 64 or type(client_time) is not int
            or not -(1 << 63) <= client_time < 1 << 63 or not _floats(coefficients) or type(joints) is not dict):
        return None
    rotations = {}
    for name, rotation in joints.items():
        if type(rotation) is not dict or rotation.keys() != {"values"} or not _floats(rotation["values"]):
            return None
        rotations[name] = pb.Rotation(values=rotation["values"])
    return pb.StreamRequest(frame=pb.FrameParams(index=index, client_time_us=client_time,
                                                 coefficients=coefficients, joints=rotations))


def parse(data: str | bytes) -> pb.StreamRequest:
    """A data-channel message as a StreamRequest: text is protobuf JSON, bytes are protobuf. Raises what
    ``json_format.Parse`` and ``FromString`` raise for a message that is not one."""
    if isinstance(data, str):
        return _plain_pose(data) or json_format.Parse(data, pb.StreamRequest())
    return pb.StreamRequest.FromString(data)
