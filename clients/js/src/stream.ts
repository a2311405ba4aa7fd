// Render streams over the WebSocket /v1/stream: the same messages as gRPC's RenderStream, in protobuf's JSON
// mapping (one StreamRequest / StreamResponse per text message). The key travels as the subprotocol
// `bearer.<key>` beside `blendsplat.v1` (a browser cannot set headers on a WebSocket; a key in the URL would be
// logged). Flow control: a frame is acknowledged when the application takes it (receive), so the server renders
// at most max_in_flight frames ahead of the reader; the newest pose wins. `render(poses)` keeps one pose in flight
// (none dropped).

import { BlendsplatError, fromStatus, timeoutError, connectionError } from "./errors.js";
import { CODECS, cameraJson, type Camera, type Pose, frameJson } from "./pose.js";

export interface StreamOptions {
  size?: number | [number, number];
  codec?: "jpeg" | "png" | "raw" | "h264";
  quality?: number;
  maxInFlight?: number;
  camera?: Camera;
  background?: [number, number, number];
  expressionNames?: string[];
  adapter?: string;
  sourceNames?: string[];
  fpsHint?: number;
  timeoutMs?: number;
}

export interface StreamHeader {
  sessionId: string;
  avatarId: string;
  expressionNames: string[];
  jointNames: string[];
  width: number;
  height: number;
  codec: string;
  maxInFlight: number;
  gaussians: number;
  /** the retargeting adapter in use ("" when none) and, with one, the order of positional coefficients */
  adapterId: string;
  sourceNames: string[];
}

export interface Frame {
  index: number;
  codec: string;
  width: number;
  height: number;
  /** the encoded image (JPEG, PNG, raw RGBA or an H.264 access unit) */
  data: Uint8Array;
  /** pose sent to frame received, on this client's clock */
  latencyMs: number;
  timings: Record<string, number>;
  dropped: number;
}

export interface FinalStatus { code: string; message: string; framesSent: number; dropped: number }

type Item = { msg: any } | { closed: { code: number; reason: string } };

function base64ToBytes(text: string): Uint8Array {
  const binary = atob(text);
  const out = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) out[i] = binary.charCodeAt(i);
  return out;
}

export class RenderStream {
  header!: StreamHeader;
  final: FinalStatus | null = null;
  private index = 0;
  private sentAt = new Map<number, number>();
  private inbox: Item[] = [];
  private waiter: (() => void) | null = null;
  private ended = false;
  private closedItem: Item | null = null;

  private constructor(private readonly ws: WebSocket, readonly timeoutMs: number) {
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") this.push({ msg: JSON.parse(ev.data) });
    };
    ws.onclose = (ev) => this.push({ closed: { code: ev.code, reason: ev.reason } });
    ws.onerror = () => undefined; // a close follows
  }

  /** Open a session (the header arrives) or throw its typed error (unknown avatar: NOT_FOUND, field avatar_id). */
  static async open(url: string, apiKey: string | undefined, avatar: string, options: StreamOptions,
                    WS: typeof WebSocket): Promise<RenderStream> {
    const protocols = apiKey ? ["blendsplat.v1", `bearer.${apiKey}`] : ["blendsplat.v1"];
    const ws = new WS(url, protocols);
    const stream = new RenderStream(ws, options.timeoutMs ?? 30000);
    const [width, height] = Array.isArray(options.size) ? options.size : [options.size ?? 512, options.size ?? 512];
    const open: Record<string, unknown> = {
      avatarId: avatar, width, height, codec: CODECS[options.codec ?? "jpeg"], quality: options.quality ?? 0,
      maxInFlight: options.maxInFlight ?? 0, fpsHint: options.fpsHint ?? 0,
    };
    if (options.camera !== undefined) open.camera = cameraJson(options.camera);
    if (options.background) open.background = { r: options.background[0], g: options.background[1], b: options.background[2] };
    if (options.expressionNames) open.expressionNames = options.expressionNames;
    if (options.adapter) open.adapter = options.adapter;
    if (options.sourceNames) open.sourceNames = options.sourceNames;
    try {
      await new Promise<void>((resolve, reject) => {
        const timer = setTimeout(() => reject(timeoutError("the WebSocket did not open in time")), stream.timeoutMs);
        ws.addEventListener("open", () => { clearTimeout(timer); resolve(); }, { once: true });
        ws.addEventListener("close", () => { clearTimeout(timer); reject(connectionError(`cannot open ${url}`)); },
          { once: true });
      });
      ws.send(JSON.stringify({ open }));
      const first = await stream.next(stream.timeoutMs);
      if (!first || !first.header) throw first ? fromStatus(first.status ?? first.error) : connectionError("closed");
      const h = first.header;
      stream.header = { sessionId: h.sessionId, avatarId: h.avatarId, expressionNames: h.expressionNames ?? [],
        jointNames: h.jointNames ?? [], width: h.width, height: h.height, codec: h.codec,
        maxInFlight: h.maxInFlight, gaussians: Number(h.gaussians ?? 0), adapterId: h.adapterId ?? "",
        sourceNames: h.sourceNames ?? [] };
    } catch (e) {
      stream.close();
      throw e;
    }
    return stream;
  }

  /** How the WebSocket closed (code, reason), once it has; null while it is open. */
  get closed(): { code: number; reason: string } | null {
    return this.closedItem && "closed" in this.closedItem ? this.closedItem.closed : null;
  }

  private push(item: Item): void {
    if ("closed" in item) this.closedItem = item;
    this.inbox.push(item);
    this.waiter?.();
  }

  private async next(timeoutMs: number): Promise<any | null> {
    const deadline = Date.now() + timeoutMs;
    while (this.inbox.length === 0) {
      const left = deadline - Date.now();
      if (left <= 0) throw timeoutError(`no reply from the stream within ${timeoutMs} ms`);
      await new Promise<void>((resolve) => {
        const timer = setTimeout(resolve, Math.min(left, 2 ** 31 - 1)); // Infinity: wait for good
        this.waiter = () => { clearTimeout(timer); resolve(); };
      });
      this.waiter = null;
    }
    const item = this.inbox.shift()!;
    if ("closed" in item) {
      this.inbox.unshift(item); // every later read sees the end
      return null;
    }
    return item.msg;
  }

  /** Send one pose; its frame index (1, 2, ...). */
  send(pose: Pose = {}): number {
    if (this.ended) throw new BlendsplatError({ code: "FAILED_PRECONDITION", message: "the stream has ended", field: "" });
    this.index += 1;
    this.sentAt.set(this.index, performance.now());
    this.ws.send(JSON.stringify({ frame: frameJson(this.index, pose) }));
    return this.index;
  }

  /** The next frame (acknowledged), or null once the stream ended (`final` holds the final status, `closed` how
   * the WebSocket closed); a refused pose throws its typed error (the stream goes on), a failed stream its final
   * status. `timeoutMs` (default: the stream's) may be Infinity. */
  async receive(timeoutMs?: number): Promise<Frame | null> {
    const msg = await this.next(timeoutMs ?? this.timeoutMs);
    if (msg === null) return null;
    if (msg.error) {
      this.sentAt.delete(Number(msg.error.frameIndex ?? 0));
      throw fromStatus(msg.error);
    }
    if (msg.status) {
      const s = msg.status;
      this.final = { code: s.code ?? "OK", message: s.message ?? "", framesSent: Number(s.framesSent ?? 0),
        dropped: Number(s.dropped ?? 0) };
      if (s.code && s.code !== "OK") throw fromStatus(s);
      return null;
    }
    const f = msg.frame;
    const index = Number(f.index ?? 0);
    const sent = this.sentAt.get(index);
    for (const old of this.sentAt.keys()) if (old <= index) this.sentAt.delete(old);
    if (this.ws.readyState === 1) this.ws.send(JSON.stringify({ ack: { index: String(index) } }));
    const t = f.timings ?? {};
    return { index, codec: f.codec ?? "CODEC_JPEG", width: f.width, height: f.height,
      data: base64ToBytes(f.data ?? ""), latencyMs: sent === undefined ? 0 : performance.now() - sent,
      timings: { queue: t.queueMs ?? 0, blend: t.blendMs ?? 0, lbs: t.lbsMs ?? 0, raster: t.rasterMs ?? 0,
        encode: t.encodeMs ?? 0, total: t.totalMs ?? 0, batch: t.batch ?? 1 },
      dropped: Number(f.dropped ?? 0) };
  }

  /** Frames of `poses`, one pose in flight at a time (none dropped). */
  async *render(poses: Iterable<Pose>, timeoutMs?: number): AsyncGenerator<Frame> {
    for (const pose of poses) {
      const index = this.send(pose);
      let frame: Frame | null;
      while ((frame = await this.receive(timeoutMs)) !== null && frame.index < index) { /* an older one */ }
      if (frame === null) return;
      yield frame;
    }
  }

  /** Stop sending: the frames still to come, until the final status. */
  async end(timeoutMs?: number): Promise<Frame[]> {
    const left: Frame[] = [];
    if (!this.ended) {
      this.ended = true;
      if (this.ws.readyState === 1) this.ws.send(JSON.stringify({ end: {} }));
    }
    let frame: Frame | null;
    while ((frame = await this.receive(timeoutMs)) !== null) left.push(frame);
    return left;
  }

  /** Close the WebSocket (after `end` for a graceful finish). */
  close(): void {
    this.ended = true;
    if (this.ws.readyState <= 1) this.ws.close(1000);
  }

  /** End gracefully (frames still to come are discarded, the final status kept) and close: use it in `finally`. */
  async finish(): Promise<void> {
    if (!this.final && !this.closedItem) {
      try { await this.end(); } catch { /* closing anyway */ }
    }
    this.close();
  }
}
