// Blendsplat WebRTC client (WHEP style): the avatar as a video track, driven over a data channel.
//
//   import { connectWebRTC } from "/static/app/webrtc.js";
//   const session = await connectWebRTC({ avatar: "demo", apiKey, video: document.querySelector("video"),
//                                         onFrame: (f) => console.log(f.index, f.latencyMs) });
//   session.sendFrame({ index: 1, namedCoefficients: { jawOpen: 0.4 } });   // FrameParams as protobuf JSON
//   await session.close();                                                   // DELETE, then the peer closes
//
// Messages on the data channel are the WebSocket stream's (service/webrtc/peer.py): the client sends
// StreamRequest JSON ({frame: ...} or {end: {}}), the server answers with the session's header, per frame sent on
// the video a timing message ({frame: {index, timings}, video: {pts, codec}}), errors and the final status.
// A decoded video frame is matched to its frame index by RTP timestamp: timestamp = origin + pts (mod 2^32) with
// one origin per stream, found as the difference most (timestamp, pts) pairs share (requestVideoFrameCallback gives
// each shown frame's rtpTimestamp). latencyMs runs from sendFrame to the frame's presentation, on this page's clock.

const WRAP = 2 ** 32;

function median(values) {
  if (!values.length) return NaN;
  const s = [...values].sort((a, b) => a - b);
  return s[Math.floor((s.length - 1) / 2)];
}

export async function connectWebRTC({ url = "", avatar, size = 512, codecs = "h264,vp8", apiKey = "", video,
                                      iceServers = [], iceTransportPolicy = "all", onHeader = () => {},
                                      onFrame = () => {}, onTiming = () => {}, onError = () => {},
                                      onStatus = () => {} } = {}) {
  const pc = new RTCPeerConnection({ iceServers, iceTransportPolicy });
  pc.addTransceiver("video", { direction: "recvonly" });
  const channel = pc.createDataChannel("blendsplat");
  const sentAt = new Map();        // frame index -> performance.now() when sent
  const byPts = new Map();         // pts -> frame index (from the timing messages)
  const votes = new Map();         // candidate origin -> count
  const early = [];                // the first frames' RTP timestamps (for the vote)
  const latencies = [];
  let origin = null;
  let location = "";
  let closed = false;
  const stats = { frames: 0, timings: 0, errors: 0, latencyP50: NaN, lastLatency: NaN, codec: "" };
  let header = null;
  let opened;
  const ready = new Promise((resolve) => { opened = resolve; });

  function vote(ts, pts) {
    const o = ((ts - pts) % WRAP + WRAP) % WRAP;
    const n = (votes.get(o) || 0) + 1;
    votes.set(o, n);
    if (n >= 3 && (origin === null || n > (votes.get(origin) || 0))) origin = o;
  }

  function indexOf(ts) {
    if (origin === null) return null;
    const pts = ((ts - origin) % WRAP + WRAP) % WRAP;
    for (const d of [0, -1, 1, -2, 2]) if (byPts.has(pts + d)) return byPts.get(pts + d);
    return null;
  }

  channel.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.header) {
      header = msg.header;
      onHeader(msg.header);
      opened();
    } else if (msg.frame) {
      stats.timings += 1;
      stats.codec = (msg.video && msg.video.codec) || stats.codec;
      if (msg.video) {
        byPts.set(Number(msg.video.pts), Number(msg.frame.index));
        if (origin === null) for (const ts of early) vote(ts, Number(msg.video.pts));
      }
      onTiming(msg);
    } else if (msg.error) {
      stats.errors += 1;
      onError(msg.error);
    } else if (msg.status) {
      onStatus(msg.status);
    }
  };

  pc.ontrack = (ev) => {
    if (ev.track.kind !== "video" || !video) return;
    video.muted = true;
    video.playsInline = true;
    video.srcObject = new MediaStream([ev.track]);
    video.play().catch(() => {});
    const shown = (now, meta) => {
      if (closed) return;
      stats.frames += 1;
      const ts = meta.rtpTimestamp;
      let index = null;
      if (ts !== undefined) {
        if (origin === null && early.length < 30) {
          early.push(ts);
          for (const pts of byPts.keys()) vote(ts, pts);
        }
        index = indexOf(ts);
      }
      let latencyMs = NaN;
      if (index !== null && sentAt.has(index)) {
        latencyMs = (meta.presentationTime || now) - sentAt.get(index);
        latencies.push(latencyMs);
        if (latencies.length > 300) latencies.shift();
        stats.lastLatency = latencyMs;
        stats.latencyP50 = median(latencies);
        for (const k of sentAt.keys()) if (k <= index) sentAt.delete(k);
      }
      onFrame({ index, latencyMs, rtpTimestamp: ts, width: meta.width, height: meta.height });
      video.requestVideoFrameCallback(shown);
    };
    video.requestVideoFrameCallback(shown);
  };

  await pc.setLocalDescription(await pc.createOffer());
  await new Promise((resolve) => {  // every host candidate in the offer (loopback and LAN gathering is quick)
    if (pc.iceGatheringState === "complete") return resolve();
    const timer = setTimeout(resolve, 3000);
    pc.addEventListener("icegatheringstatechange", () => {
      if (pc.iceGatheringState === "complete") { clearTimeout(timer); resolve(); }
    });
  });
  const query = new URLSearchParams({ avatar, size: String(size), codecs });
  const resp = await fetch(`${url}/v1/webrtc?${query}`, {
    method: "POST", body: pc.localDescription.sdp,
    headers: { "Content-Type": "application/sdp", ...(apiKey ? { Authorization: `Bearer ${apiKey}` } : {}) },
  });
  if (resp.status !== 201) {
    pc.close();
    let message = `HTTP ${resp.status}`;
    try { message = (await resp.json()).error.message || message; } catch (e) { /* not JSON */ }
    const err = new Error(`POST /v1/webrtc: ${message}`);
    err.status = resp.status;
    throw err;
  }
  location = new URL(resp.headers.get("Location"), resp.url).href;
  await pc.setRemoteDescription({ type: "answer", sdp: await resp.text() });

  const session = {
    pc, channel, stats,
    get header() { return header; },
    get location() { return location; },
    ready,
    send(request) {
      if (channel.readyState === "open") channel.send(JSON.stringify(request));
    },
    sendFrame(frame) {
      sentAt.set(Number(frame.index), performance.now());
      session.send({ frame });
    },
    async close() {
      if (closed) return;
      closed = true;
      try {
        await fetch(location, { method: "DELETE", headers: apiKey ? { Authorization: `Bearer ${apiKey}` } : {} });
      } catch (e) { /* the server frees it anyway when the peer goes */ }
      pc.close();
    },
  };
  return session;
}
