// The WebRTC session (WHEP style): the avatar as a video track, driven over a data channel. Browsers only
// (RTCPeerConnection); the /demo page's WebRTC mode uses it, and the server serves it as /static/app/webrtc.js.
//
//   import { connectWebRTC } from "/static/app/webrtc.js";
//   const session = await connectWebRTC({ avatar: "demo", apiKey, video: document.querySelector("video"),
//                                         onFrame: (f) => console.log(f.index, f.latencyMs) });
//   await session.ready;                                                   // the session's header arrived
//   session.sendPose({ expression: { jawOpen: 0.4 } });                    // or sendFrame(FrameParams JSON)
//   await session.close();                                                 // DELETE, then the peer closes
//
// Signalling: POST /v1/webrtc?avatar&size&codecs with the offer (every host candidate gathered first), 201 with
// the answer, its Location (DELETE closes it) and the server's ICE servers as WHEP `Link: <turn:...>;
// rel="ice-server"; username="..."; credential="..."` headers. Without `iceServers` from the caller, a server that
// lists ICE servers gets a second offer gathered through them (the first session is deleted before it connects):
// a page needs no TURN configuration of its own.
//
// Messages on the data channel are the WebSocket stream's (service/webrtc/peer.py): the client sends
// StreamRequest JSON ({frame: ...} or {end: {}}), the server answers with the session's header, per frame sent on
// the video a timing message ({frame: {index, timings}, video: {pts, codec}}), errors and the final status.
// A decoded video frame is matched to its frame index by RTP timestamp: timestamp = origin + pts (mod 2^32) with
// one origin per stream, found as the difference most (timestamp, pts) pairs share (requestVideoFrameCallback gives
// each shown frame's rtpTimestamp). latencyMs runs from sendFrame to the frame's presentation, on this page's clock.
import { fromResponse } from "./errors.js";
import { frameJson } from "./pose.js";
const WRAP = 2 ** 32;
function median(values) {
    if (!values.length)
        return NaN;
    const s = [...values].sort((a, b) => a - b);
    return s[Math.floor((s.length - 1) / 2)];
}
/** The ICE servers of WHEP `Link` header values (`<URL>; rel="ice-server"; username="..."; credential="..."`),
 * several in one header (as fetch joins them: ", ") or one per item. Other links are left out. */
export function parseIceServers(links) {
    const text = Array.isArray(links) ? links.join(", ") : links ?? "";
    const servers = [];
    let i = 0;
    const space = () => { while (i < text.length && /[ \t]/.test(text[i]))
        i++; };
    while (i < text.length) {
        const open = text.indexOf("<", i);
        const close = open < 0 ? -1 : text.indexOf(">", open);
        if (close < 0)
            break;
        const url = text.slice(open + 1, close).trim();
        i = close + 1;
        const params = {};
        for (;;) {
            space();
            if (text[i] !== ";")
                break;
            i++;
            space();
            const name = /^[A-Za-z0-9!#$%&'*+.^_`|~-]+/.exec(text.slice(i))?.[0] ?? "";
            if (!name)
                break;
            i += name.length;
            space();
            let value = "";
            if (text[i] === "=") {
                i++;
                space();
                if (text[i] === '"') {
                    for (i++; i < text.length && text[i] !== '"'; i++)
                        value += text[i] === "\\" ? text[++i] ?? "" : text[i];
                    i++;
                }
                else {
                    const token = /^[^;,\s]*/.exec(text.slice(i))[0];
                    value = token;
                    i += token.length;
                }
            }
            params[name.toLowerCase()] = value;
        }
        if (url && (params.rel ?? "").split(/\s+/).includes("ice-server")) {
            const server = { urls: url };
            if (params.username !== undefined)
                server.username = params.username;
            if (params.credential !== undefined)
                server.credential = params.credential;
            servers.push(server);
        }
    }
    return servers;
}
/** Connect a WebRTC session to the avatar: resolves once the answer is set (await `session.ready` for the header);
 * a refused offer throws the service's typed error (BlendsplatError: code, message, field, httpStatus). */
export async function connectWebRTC(options) {
    const base = (options.url ?? globalThis.location?.origin ?? "").replace(/\/+$/, "");
    const auth = options.apiKey ? { Authorization: `Bearer ${options.apiKey}` } : {};
    const pc = new RTCPeerConnection({ iceServers: options.iceServers ?? [],
        iceTransportPolicy: options.iceTransportPolicy ?? "all" });
    pc.addTransceiver("video", { direction: "recvonly" });
    const channel = pc.createDataChannel("blendsplat");
    await pc.setLocalDescription(await pc.createOffer());
    await new Promise((resolve) => {
        if (pc.iceGatheringState === "complete")
            return resolve();
        const timer = setTimeout(resolve, 3000);
        pc.addEventListener("icegatheringstatechange", () => {
            if (pc.iceGatheringState === "complete") {
                clearTimeout(timer);
                resolve();
            }
        });
    });
    const query = new URLSearchParams({ avatar: options.avatar, size: String(options.size ?? 512),
        codecs: options.codecs ?? "h264,vp8" });
    let resp;
    try {
        resp = await fetch(`${base}/v1/webrtc?${query}`, { method: "POST", body: pc.localDescription.sdp,
            headers: { "Content-Type": "application/sdp", ...auth } });
    }
    catch (e) {
        pc.close();
        throw e;
    }
    if (resp.status !== 201) {
        pc.close();
        throw await fromResponse(resp);
    }
    const location = new URL(resp.headers.get("Location") ?? "", resp.url).href;
    const listed = parseIceServers(resp.headers.get("Link"));
    if (options.iceServers === undefined && listed.length) {
        // the server's ICE servers (TURN, STUN): this offer did not gather through them; offer again with them
        pc.close();
        await fetch(location, { method: "DELETE", headers: auth }).catch(() => undefined);
        return connectWebRTC({ ...options, iceServers: listed });
    }
    return attach(pc, channel, location, options, auth, await resp.text());
}
// The session's handlers (data channel, video frames, RTP matching) on a peer connection whose offer was answered.
async function attach(pc, channel, location, options, auth, answer) {
    const { video } = options;
    const noop = () => undefined;
    const onHeader = options.onHeader ?? noop, onFrame = options.onFrame ?? noop;
    const onTiming = options.onTiming ?? noop, onError = options.onError ?? noop;
    const onStatus = options.onStatus ?? noop;
    const sentAt = new Map(); // frame index -> performance.now() when sent
    const byPts = new Map(); // pts -> frame index (from the timing messages)
    const votes = new Map(); // candidate origin -> count
    const early = []; // the first frames' RTP timestamps (for the vote)
    const latencies = [];
    let origin = null;
    let closed = false;
    let header = null;
    let nextIndex = 1;
    const stats = { frames: 0, timings: 0, errors: 0, latencyP50: NaN, lastLatency: NaN, codec: "" };
    let opened;
    const ready = new Promise((resolve) => { opened = resolve; });
    function vote(ts, pts) {
        const o = ((ts - pts) % WRAP + WRAP) % WRAP;
        const n = (votes.get(o) ?? 0) + 1;
        votes.set(o, n);
        if (n >= 3 && (origin === null || n > (votes.get(origin) ?? 0)))
            origin = o;
    }
    function indexOf(ts) {
        if (origin === null)
            return null;
        const pts = ((ts - origin) % WRAP + WRAP) % WRAP;
        for (const d of [0, -1, 1, -2, 2])
            if (byPts.has(pts + d))
                return byPts.get(pts + d);
        return null;
    }
    channel.onmessage = (ev) => {
        const msg = JSON.parse(ev.data);
        if (msg.header) {
            header = msg.header;
            onHeader(msg.header);
            opened();
        }
        else if (msg.frame) {
            stats.timings += 1;
            stats.codec = msg.video?.codec || stats.codec;
            if (msg.video) {
                byPts.set(Number(msg.video.pts), Number(msg.frame.index));
                if (origin === null)
                    for (const ts of early)
                        vote(ts, Number(msg.video.pts));
            }
            onTiming(msg);
        }
        else if (msg.error) {
            stats.errors += 1;
            onError(msg.error);
        }
        else if (msg.status) {
            onStatus(msg.status);
        }
    };
    pc.ontrack = (ev) => {
        if (ev.track.kind !== "video" || !video)
            return;
        video.muted = true;
        video.playsInline = true;
        video.srcObject = new MediaStream([ev.track]);
        video.play().catch(noop);
        const shown = (now, meta) => {
            if (closed)
                return;
            stats.frames += 1;
            const ts = meta.rtpTimestamp;
            let index = null;
            if (ts !== undefined) {
                if (origin === null && early.length < 30) {
                    early.push(ts);
                    for (const pts of byPts.keys())
                        vote(ts, pts);
                }
                index = indexOf(ts);
            }
            let latencyMs = NaN;
            if (index !== null && sentAt.has(index)) {
                latencyMs = (meta.presentationTime || now) - sentAt.get(index);
                latencies.push(latencyMs);
                if (latencies.length > 300)
                    latencies.shift();
                stats.lastLatency = latencyMs;
                stats.latencyP50 = median(latencies);
                for (const k of sentAt.keys())
                    if (k <= index)
                        sentAt.delete(k);
            }
            onFrame({ index, latencyMs, rtpTimestamp: ts, width: meta.width, height: meta.height });
            video.requestVideoFrameCallback(shown);
        };
        video.requestVideoFrameCallback(shown);
    };
    await pc.setRemoteDescription({ type: "answer", sdp: answer });
    const session = {
        pc, channel, stats, ready,
        get header() { return header; },
        get location() { return location; },
        get iceServers() { return options.iceServers ?? []; },
        send(request) {
            if (channel.readyState === "open")
                channel.send(JSON.stringify(request));
        },
        sendFrame(frame) {
            sentAt.set(Number(frame.index), performance.now());
            session.send({ frame });
        },
        sendPose(pose = {}) {
            const index = nextIndex++;
            session.sendFrame(frameJson(index, pose));
            return index;
        },
        async close() {
            if (closed)
                return;
            closed = true;
            try {
                await fetch(location, { method: "DELETE", headers: auth });
            }
            catch { /* the server frees it anyway when the peer goes */ }
            pc.close();
        },
    };
    return session;
}
