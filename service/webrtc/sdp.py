"""The SDP a client sends: the offer of ``POST /v1/webrtc`` and the trickle-ICE fragments of ``PATCH``.

Every refusal is :class:`~service.errors.InvalidArgument` (422) on field ``sdp`` whose message says what is wrong
with the SDP, before aiortc sees it: not UTF-8 text, no ``v=0`` first line, a line that is not ``x=...``, no video
section the server may send on (``recvonly`` or ``sendrecv``), no data channel (``m=application ...
webrtc-datachannel``: the driving frames come on it), none of the video codecs asked for, no ICE credentials or DTLS
fingerprint. Remote candidates that :func:`~.ice.remote_allowed` refuses are removed from the offer and from
fragments (never a target).
"""

from __future__ import annotations

import re

from ..errors import InvalidArgument
from .ice import remote_allowed

CODEC_NAMES = {"h264": "H264", "vp8": "VP8"}  # the codecs query's names -> SDP rtpmap encoding names
_LINE = re.compile(r"^[a-z]=")


def _refuse(message: str) -> InvalidArgument:
    return InvalidArgument(f"SDP offer: {message}", field="sdp")


def parse_codecs(text: str) -> list[str]:
    """``h264,vp8`` -> the SDP encoding names in the client's order of preference (422 naming ``codecs``)."""
    names = [part.strip().lower() for part in text.split(",") if part.strip()]
    unknown = [n for n in names if n not in CODEC_NAMES]
    if not names or unknown:
        raise InvalidArgument(f"codecs must be a comma list of {', '.join(CODEC_NAMES)}; got {text[:100]!r}",
                              field="codecs")
    return list(dict.fromkeys(CODEC_NAMES[n] for n in names))


def _text(body: bytes) -> list[str]:
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise _refuse("the body is not UTF-8 text") from None
    return [line for line in re.split(r"\r?\n", text.strip()) if line]


def _candidate_host(line: str) -> str:
    """The connection address of an ``a=candidate:`` line (its fifth field)."""
    parts = line.split(":", 1)[1].split() if ":" in line else []
    return parts[4] if len(parts) > 4 else ""


def _keep(line: str) -> bool:
    return not line.startswith("a=candidate:") or remote_allowed(_candidate_host(line))


def check_offer(body: bytes, codecs: list[str]) -> str:
    """The offer as aiortc's input (CRLF lines, refused remote candidates left out), or a 422 naming the problem."""
    lines = _text(body)
    if not lines or lines[0].strip() != "v=0":
        raise _refuse("not a session description (the first line must be v=0)")
    for number, line in enumerate(lines, 1):
        if not _LINE.match(line):
            raise _refuse(f"line {number} is not of the form x=value: {line[:80]!r}")
    sections: list[list[str]] = []
    for line in lines:
        if line.startswith("m="):
            sections.append([line])
        elif sections:
            sections[-1].append(line)
    videos = [s for s in sections if s[0].startswith("m=video ")]
    if not videos:
        raise _refuse("no m=video section: the avatar comes as a video track (add a recvonly video transceiver)")
    if all(any(a in ("a=sendonly", "a=inactive") for a in s) for s in videos):
        raise _refuse("the video section is sendonly or inactive; the server sends video: make it recvonly")
    if not any(s[0].startswith("m=application ") and "webrtc-datachannel" in s[0] for s in sections):
        raise _refuse("no data channel (m=application ... webrtc-datachannel): the driving frames come on a data "
                      "channel; create one before the offer")
    offered = {m.group(1).upper() for s in videos for line in s
               if (m := re.match(r"^a=rtpmap:\d+ ([A-Za-z0-9-]+)/", line))}
    if not offered & set(codecs):
        has = ", ".join(sorted(offered)) or "none"
        raise _refuse(f"no video codec of {', '.join(codecs)} offered (the offer has {has})")
    text = "\n".join(lines)
    for needed in ("a=ice-ufrag:", "a=ice-pwd:", "a=fingerprint:"):
        if needed not in text:
            raise _refuse(f"no {needed[:-1]} line (ICE credentials and a DTLS fingerprint are required)")
    return "\r\n".join(line for line in lines if _keep(line)) + "\r\n"


def parse_fragment(body: bytes) -> tuple[list[tuple[str | None, str]], bool]:
    """A trickle-ICE fragment (``application/trickle-ice-sdpfrag``, RFC 8840): its candidates as (mid, the
    candidate's SDP without ``a=``), refused ones left out, and whether it ends the candidates. An ICE restart
    (new credentials) is not supported: 422."""
    mid: str | None = None
    candidates, end = [], False
    for line in _text(body):
        if line.startswith("a=mid:"):
            mid = line[6:].strip()
        elif line.startswith("a=candidate:"):
            if _keep(line):
                candidates.append((mid, line[2:]))
        elif line.strip() == "a=end-of-candidates":
            end = True
        elif line.startswith(("a=ice-ufrag:", "a=ice-pwd:")):
            continue  # the session's own credentials (an ICE restart would need an offer: not supported)
        elif not _LINE.match(line):
            raise InvalidArgument(f"SDP fragment: not of the form x=value: {line[:80]!r}", field="sdp")
    return candidates, end
