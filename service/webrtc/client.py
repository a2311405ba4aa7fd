"""A Python WebRTC client of the service (aiortc): what `blendsplat bench webrtc`, `blendsplat live` and the tests use.

:class:`WhepClient` offers a recvonly video transceiver and a data channel, POSTs the offer to ``/v1/webrtc``
(the key as a bearer token), sends frames on the data channel as protobuf JSON, and records every decoded video
frame's RTP timestamp and arrival time and every data-channel reply. With ``decode=False`` it records each frame as
it completes (its last packet) and decodes nothing until :meth:`WhepClient.decode_recorded`, after the run: a
benchmark client on the server's own cores then takes no decoder's CPU from it (the gRPC bench decodes no JPEG
either), and latency runs to the frame received, as the gRPC bench's does.

Frames are matched to indices by RTP timestamp (:func:`match_indices`): the server's timing message of each frame
carries its ``video.pts``, and a frame's RTP timestamp is ``(origin + pts) mod 2**32`` with one random origin per
stream; the origin is the difference that most (timestamp, pts) pairs share (wall-clock presentation times make a
wrong one match at most by chance), and a timestamp matches a pts within 2 ticks (aiortc's VP8 path rounds the
time-base conversion; frames are at least a millisecond, 90 ticks, apart).

aiortc's receiver completes a video frame only when the next frame's first packet arrives, a frame interval late;
this client completes it at its RTP marker bit (the frame's last packet, as browsers do), so latencies are the
server's and the network's, not the receiver's wait. ``MarkerJitterBuffer`` replaces aiortc's buffer class in this
process for that (aiortc 1.16.x, pinned); it also counts the video bitstream's bytes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlencode, urljoin

import aiortc.rtcrtpreceiver
import httpx
import numpy as np
from aiortc import RTCConfiguration, RTCIceServer, RTCPeerConnection, RTCSessionDescription
from aiortc.jitterbuffer import JitterBuffer, JitterFrame
from aiortc.mediastreams import MediaStreamError
from aiortc.rtcconfiguration import RTCIceTransportPolicy

RTP_WRAP = 1 << 32


class MarkerJitterBuffer(JitterBuffer):
    """aiortc's jitter buffer, but a video frame is complete at its marker bit (all its packets in order)."""

    def __init__(self, capacity: int, prefetch: int = 0, is_video: bool = False) -> None:
        super().__init__(capacity, prefetch, is_video)
        self.bytes = 0  # the video bitstream's bytes in frames handed out
        self.take: Callable[[JitterFrame], None] | None = None  # set: complete frames go here, not to the decoder

    def add(self, packet) -> tuple[bool, JitterFrame | None]:
        pli, frame = super().add(packet)
        if frame is not None and self.take is not None:
            self.take(frame)
            return pli, None
        return pli, frame

    def _remove_frame(self, sequence_number: int) -> JitterFrame | None:
        frame = self._marker_frame() if self._is_video else None
        frame = frame or super()._remove_frame(sequence_number)
        if frame is not None:
            self.bytes += len(frame.data)
        return frame

    def _marker_frame(self) -> JitterFrame | None:
        packets, timestamp = [], None
        for count in range(self.capacity):
            packet = self._packets[(self._origin + count) % self._capacity]
            if packet is None or (timestamp is not None and packet.timestamp != timestamp):
                return None
            timestamp = packet.timestamp
            packets.append(packet)
            if packet.marker:
                self.remove(count + 1)
                return JitterFrame(data=b"".join(p._data for p in packets), timestamp=timestamp)
        return None


aiortc.rtcrtpreceiver.JitterBuffer = MarkerJitterBuffer


class ClientError(RuntimeError):
    """The service refused the session (its status and error body), or it never connected."""


@dataclass
class Received:
    ts: int  # RTP timestamp
    at: float  # time.perf_counter() when it was decoded
    image: np.ndarray | None = None  # RGB [H, W, 3] uint8, for the frames kept


@dataclass
class WhepClient:
    url: str  # http://HOST:PORT
    avatar: str
    size: int = 512
    codecs: str = "h264,vp8"
    api_key: str | None = None
    keep: Callable[[int], bool] = lambda n: False  # which received frames (by arrival number) keep their pixels
    header: dict = field(default_factory=dict)
    frames: list[Received] = field(default_factory=list)
    timings: list[dict] = field(default_factory=list)  # the server's per-frame messages
    errors: list[dict] = field(default_factory=list)
    status: dict | None = None
    location: str = ""
    links: list[str] = field(default_factory=list)
    ice_servers: list[RTCIceServer] = field(default_factory=list)  # e.g. ice_servers_of(links) of a session before
    relay_only: bool = False  # gather relay candidates only (through the TURN servers of ice_servers)
    decode: bool = True  # False: frames are recorded as they arrive and decoded by decode_recorded(), after the run

    def __post_init__(self) -> None:
        self.pc: RTCPeerConnection | None = None
        self.channel = None
        self._opened = asyncio.Event()
        self._ended = asyncio.Event()
        self._reader: asyncio.Task | None = None
        self._encoded: list[tuple[Received, JitterFrame, bool]] = []  # decode off: (arrival, bitstream, keep pixels)
        self._http = httpx.AsyncClient(timeout=30.0, headers=(
            {"Authorization": f"Bearer {self.api_key}"} if self.api_key else {}))

    async def open(self, timeout: float = 30.0) -> None:
        """Offer, answer, and wait for the data channel's header (ClientError when refused or not connected)."""
        pc = self.pc = RTCPeerConnection(RTCConfiguration(
            iceServers=self.ice_servers,
            iceTransportPolicy=RTCIceTransportPolicy.RELAY if self.relay_only else RTCIceTransportPolicy.ALL))
        transceiver = pc.addTransceiver("video", direction="recvonly")
        if not self.decode:  # aiortc 1.16 (pinned): the receiver's private jitter buffer, made with the transceiver
            transceiver.receiver._RTCRtpReceiver__jitter_buffer.take = self._arrived
        self.channel = channel = pc.createDataChannel("blendsplat")
        channel.on("message", self._message)
        pc.on("track", lambda track: self._start_reader(track))
        await pc.setLocalDescription(await pc.createOffer())
        query = urlencode({"avatar": self.avatar, "size": self.size, "codecs": self.codecs})
        r = await self._http.post(f"{self.url}/v1/webrtc?{query}", content=pc.localDescription.sdp,
                                  headers={"Content-Type": "application/sdp"})
        if r.status_code != 201:
            await pc.close()
            raise ClientError(f"POST /v1/webrtc answered {r.status_code}: {r.text[:500]}")
        self.location = urljoin(self.url + "/", r.headers["location"])
        self.links = r.headers.get_list("link")
        await pc.setRemoteDescription(RTCSessionDescription(sdp=r.text, type="answer"))
        try:
            await asyncio.wait_for(self._opened.wait(), timeout)
        except TimeoutError:
            await self.close()
            raise ClientError(f"no data channel header within {timeout:g} s (ICE {pc.iceConnectionState})") from None

    def _start_reader(self, track) -> None:
        if track.kind == "video" and self._reader is None:
            self._reader = asyncio.ensure_future(self._read(track))

    async def _read(self, track) -> None:
        n = 0
        with contextlib.suppress(MediaStreamError):
            while True:
                frame = await track.recv()
                received = Received(int(frame.pts), time.perf_counter())
                if self.keep(n):
                    received.image = frame.to_ndarray(format="rgb24")
                self.frames.append(received)
                n += 1

    def _arrived(self, frame: JitterFrame) -> None:
        """A complete encoded frame (``decode`` off): its arrival now, its bitstream kept for later."""
        received = Received(frame.timestamp, time.perf_counter())
        self._encoded.append((received, frame, self.keep(len(self.frames))))
        self.frames.append(received)

    def decode_recorded(self) -> None:
        """Decode the frames recorded with ``decode`` off, in arrival order, with aiortc's decoder of the negotiated
        codec, and give the kept ones their pixels (a frame that does not decode keeps none)."""
        import av
        from aiortc.codecs import get_decoder

        codec = next(c for c in self.pc.getTransceivers()[0]._codecs if not c.mimeType.lower().endswith("/rtx"))
        decoder, kept = get_decoder(codec), {}
        for received, frame, keep in self._encoded:
            if keep:
                kept[received.ts] = received
            with contextlib.suppress(av.FFmpegError):
                for image in decoder.decode(frame):
                    if (target := kept.pop(int(image.pts), None)) is not None:
                        target.image = image.to_ndarray(format="rgb24")
        self._encoded = []

    def _message(self, data: str | bytes) -> None:
        body = json.loads(data)
        if "header" in body:
            self.header = body["header"]
            self._opened.set()
        elif "frame" in body:
            self.timings.append(body)
        elif "error" in body:
            self.errors.append(body["error"])
        elif "status" in body:
            self.status = body["status"]
            self._ended.set()

    def send(self, request: dict) -> None:
        """One StreamRequest as protobuf JSON, e.g. ``{"frame": {"index": 1, "coefficients": [...]}}``."""
        self.channel.send(json.dumps(request))

    async def wait_status(self, timeout: float) -> dict | None:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._ended.wait(), timeout)
        return self.status

    def video_bytes(self) -> int:
        """The video bitstream's bytes received so far."""
        total = 0
        for receiver in self.pc.getReceivers() if self.pc else []:
            buffer = getattr(receiver, "_RTCRtpReceiver__jitter_buffer", None)
            total += getattr(buffer, "bytes", 0)
        return total

    async def close(self, delete: bool = True) -> None:
        if delete and self.location:
            with contextlib.suppress(httpx.HTTPError):
                await self._http.delete(self.location)
        if self._reader is not None:
            self._reader.cancel()
        if self.pc is not None:
            await self.pc.close()
        await self._http.aclose()


def use_loopback_if_local(url: str) -> None:
    """This client's ICE on 127.0.0.1 only when the service is on a loopback address (or
    BLENDSPLAT_WEBRTC_HOST_ADDRESSES says which addresses): no other address is then offered or ever a target."""
    import os
    from urllib.parse import urlsplit

    from . import ice

    chosen = [a.strip() for a in os.environ.get("BLENDSPLAT_WEBRTC_HOST_ADDRESSES", "").split(",") if a.strip()]
    host = urlsplit(url).hostname or ""
    if not chosen and host in ("127.0.0.1", "localhost", "::1"):
        chosen = ["::1"] if host == "::1" else ["127.0.0.1"]
    if chosen:
        ice.use_host_addresses(chosen)


def ice_servers_of(links: list[str]) -> list[RTCIceServer]:
    """The ICE servers of WHEP ``Link: <URL>; rel="ice-server"; username="..."; credential="..."`` values."""
    servers = []
    for link in links:
        url = link[link.find("<") + 1:link.find(">")]
        params = dict(re.findall(r'(\w[\w-]*)="((?:[^"\\]|\\.)*)"', link))
        if params.get("rel") == "ice-server" and url:
            servers.append(RTCIceServer(urls=url, username=params.get("username"),
                                        credential=params.get("credential")))
    return servers


def match_indices(frames: list[Received], timings: list[dict]) -> list[int | None]:
    """The frame index each received video frame shows (None: no timing message matches it)."""
    by_pts = {int(t["video"]["pts"]): int(t["frame"]["index"]) for t in timings if "video" in t}
    if not frames or not by_pts:
        return [None] * len(frames)
    early = list(by_pts)[:300]
    votes = Counter((f.ts - pts) % RTP_WRAP for f in frames[:30] for pts in early)
    origin = votes.most_common(1)[0][0]

    def index(ts: int) -> int | None:  # aiortc's time-base conversion may round a timestamp by one tick
        pts = (ts - origin) % RTP_WRAP
        return next((by_pts[p] for p in (pts, pts - 1, pts + 1, pts - 2, pts + 2) if p in by_pts), None)

    return [index(f.ts) for f in frames]
