// The REST API (avatars, adapters, uploads, training jobs with live events) and render streams, with retries of
// idempotent calls (GET, PUT, DELETE; POST /v1/jobs with an Idempotency-Key) on 408, 429, 5xx and network
// failures, with backoff and jitter, honouring Retry-After; a timeout on every call.

import { BlendsplatError, connectionError, fromResponse, timeoutError } from "./errors.js";
import { RenderStream, type StreamOptions } from "./stream.js";

export interface RetryPolicy { attempts: number; backoffMs: number; maxBackoffMs: number; maxRetryAfterMs: number }

export interface ClientOptions {
  /** the HTTP base URL, e.g. http://127.0.0.1:8080 (default: this page's origin in a browser) */
  url?: string;
  /** an API key or a session token: never a secret key in a web page (README) */
  apiKey?: string;
  timeoutMs?: number;
  retry?: Partial<RetryPolicy>;
  fetch?: typeof fetch;
  WebSocket?: typeof WebSocket;
}

export interface JobEvent { event: string; data: Record<string, any>; id?: string }

interface RequestOptions {
  query?: Record<string, string | number | undefined>;
  json?: unknown;
  body?: () => BodyInit;
  headers?: Record<string, string>;
  timeoutMs?: number;
  read?: "json" | "bytes" | "none";
}

const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);
const IDEMPOTENT = new Set(["GET", "HEAD", "PUT", "DELETE"]);
const sleep = (ms: number) => new Promise((resolve) => setTimeout(resolve, ms));
const seg = (id: string) => encodeURIComponent(id);

export class Client {
  readonly url: string;
  readonly timeoutMs: number;
  readonly retry: RetryPolicy;
  private readonly apiKey?: string;
  private readonly fetchImpl: typeof fetch;
  private readonly WS?: typeof WebSocket;

  constructor(options: ClientOptions = {}) {
    const origin = (globalThis as any).location?.origin as string | undefined;
    this.url = (options.url ?? origin ?? "http://127.0.0.1:8080").replace(/\/+$/, "");
    this.apiKey = options.apiKey;
    this.timeoutMs = options.timeoutMs ?? 30000;
    this.retry = { attempts: 4, backoffMs: 250, maxBackoffMs: 8000, maxRetryAfterMs: 60000, ...options.retry };
    this.fetchImpl = options.fetch ?? globalThis.fetch.bind(globalThis);
    this.WS = options.WebSocket ?? (globalThis as any).WebSocket;
  }

  private headers(extra: Record<string, string> = {}): Record<string, string> {
    return { Accept: "application/json", ...(this.apiKey ? { Authorization: `Bearer ${this.apiKey}` } : {}), ...extra };
  }

  private delay(attempt: number, error: BlendsplatError, idempotent: boolean): number | null {
    if (!idempotent || attempt + 1 >= this.retry.attempts) return null;
    const status = error.httpStatus;
    const retryable = status === undefined ? error.code === "UNAVAILABLE"
      : status === 408 || status === 429 || (status >= 500 && status !== 501);
    if (!retryable) return null;
    if (error.retryAfterMs !== undefined) return error.retryAfterMs <= this.retry.maxRetryAfterMs ? error.retryAfterMs : null;
    const step = Math.min(this.retry.maxBackoffMs, this.retry.backoffMs * 2 ** attempt);
    return step * (0.5 + Math.random() / 2);
  }

  /** One API call with the client's key, timeout and retries; the JSON answer (or bytes, or nothing). */
  async request(method: string, path: string, options: RequestOptions = {}): Promise<any> {
    const headers = this.headers(options.headers);
    const idempotent = IDEMPOTENT.has(method) || (method === "POST" && path === "/v1/jobs" && "Idempotency-Key" in headers);
    const query = Object.entries(options.query ?? {}).filter(([, v]) => v !== undefined)
      .map(([k, v]) => `${encodeURIComponent(k)}=${encodeURIComponent(String(v))}`).join("&");
    const url = `${this.url}${path}${query ? `?${query}` : ""}`;
    for (let attempt = 0; ; attempt++) {
      let error: BlendsplatError;
      const controller = new AbortController();
      const timer = setTimeout(() => controller.abort(), options.timeoutMs ?? this.timeoutMs);
      try {
        const body = options.json !== undefined ? JSON.stringify(options.json) : options.body?.();
        if (options.json !== undefined) headers["Content-Type"] = "application/json";
        const response = await this.fetchImpl(url, { method, headers, body, signal: controller.signal,
          ...(body instanceof ReadableStream ? { duplex: "half" } : {}) } as RequestInit);
        if (response.ok) {
          if (options.read === "none" || response.status === 204) return null;
          if (options.read === "bytes") return new Uint8Array(await response.arrayBuffer());
          return await response.json();
        }
        error = await fromResponse(response);
      } catch (e) {
        if (e instanceof BlendsplatError) throw e;
        if (controller.signal.aborted) throw timeoutError(`${method} ${path}: no answer in time`);
        error = connectionError(`${method} ${path}: cannot reach ${this.url} (${(e as Error).message})`);
      } finally {
        clearTimeout(timer);
      }
      const wait = this.delay(attempt, error, idempotent);
      if (wait === null) throw error;
      await sleep(wait);
    }
  }

  // ------------------------------------------------------------------------------------------ avatars, adapters
  async listAvatars(): Promise<any[]> { return (await this.request("GET", "/v1/avatars")).avatars; }
  getAvatar(id: string): Promise<any> { return this.request("GET", `/v1/avatars/${seg(id)}`); }
  putAvatar(id: string, bundle: Blob | Uint8Array): Promise<any> {
    return this.request("PUT", `/v1/avatars/${seg(id)}`, { body: () => bundle as BodyInit,
      headers: { "Content-Type": "application/octet-stream" }, timeoutMs: Math.max(this.timeoutMs, 300000) });
  }
  deleteAvatar(id: string): Promise<null> { return this.request("DELETE", `/v1/avatars/${seg(id)}`, { read: "none" }); }
  async listAdapters(): Promise<any[]> { return (await this.request("GET", "/v1/adapters")).adapters; }
  getAdapter(id: string): Promise<any> { return this.request("GET", `/v1/adapters/${seg(id)}`); }
  deleteAdapter(id: string): Promise<any> { return this.request("DELETE", `/v1/adapters/${seg(id)}`); }

  // ------------------------------------------------------------------------------------------ uploads
  /** POST /v1/uploads: a dataset archive or a video as the multipart field `file`; `onProgress(sent, total)`
   * as the body is read. Not retried (not idempotent). */
  upload(file: Blob | Uint8Array, options: { filename?: string; onProgress?: (sent: number, total: number) => void;
    timeoutMs?: number } = {}): Promise<any> {
    const blob = file instanceof Blob ? file : new Blob([file as BlobPart]);
    const name = (options.filename ?? (file as File).name ?? "upload").replace(/["\r\n]/g, "_");
    const boundary = `blendsplat-${crypto.randomUUID()}`;
    const whole = new Blob([`--${boundary}\r\nContent-Disposition: form-data; name="file"; filename="${name}"\r\n` +
      "Content-Type: application/octet-stream\r\n\r\n", blob, `\r\n--${boundary}--\r\n`]);
    const progress = options.onProgress;
    const body = () => {
      if (!progress) return whole;
      let sent = 0;
      return whole.stream().pipeThrough(new TransformStream<Uint8Array, Uint8Array>({
        transform(chunk, out) {
          sent += chunk.byteLength;
          out.enqueue(chunk);
          progress(Math.min(sent, blob.size), blob.size);
        },
      }));
    };
    return this.request("POST", "/v1/uploads", { body, timeoutMs: options.timeoutMs ?? 600000,
      headers: { "Content-Type": `multipart/form-data; boundary=${boundary}` } });
  }
  async listUploads(): Promise<any[]> { return (await this.request("GET", "/v1/uploads")).uploads; }
  getUpload(id: string): Promise<any> { return this.request("GET", `/v1/uploads/${seg(id)}`); }
  deleteUpload(id: string): Promise<null> { return this.request("DELETE", `/v1/uploads/${seg(id)}`, { read: "none" }); }

  // ------------------------------------------------------------------------------------------ jobs
  /** POST /v1/jobs with an Idempotency-Key (a fresh one unless given; null: none), so a retry makes no second job. */
  submitJob(spec: Record<string, unknown> & { upload_id: string }, idempotencyKey: string | null = crypto.randomUUID()
  ): Promise<any> {
    return this.request("POST", "/v1/jobs", { json: spec,
      headers: idempotencyKey ? { "Idempotency-Key": idempotencyKey } : {} });
  }
  getJob(id: string): Promise<any> { return this.request("GET", `/v1/jobs/${seg(id)}`); }
  cancelJob(id: string): Promise<any> { return this.request("POST", `/v1/jobs/${seg(id)}/cancel`); }
  deleteJob(id: string): Promise<null> { return this.request("DELETE", `/v1/jobs/${seg(id)}`, { read: "none" }); }
  artefact(id: string, name: string): Promise<Uint8Array> {
    return this.request("GET", `/v1/jobs/${seg(id)}/artefacts/${seg(name)}`, { read: "bytes" });
  }

  /** Every job, newest first, page after page (GET /v1/jobs cursors). */
  async *jobs(options: { state?: string; pageSize?: number } = {}): AsyncGenerator<any> {
    let cursor: string | undefined;
    do {
      const page = await this.request("GET", "/v1/jobs", { query: { state: options.state,
        limit: options.pageSize ?? 50, cursor } });
      yield* page.jobs;
      cursor = page.next_cursor ?? undefined;
    } while (cursor);
  }

  /** GET /v1/jobs/{id}/events: the job's server-sent events (after `lastEventId`) until the server closes. */
  async *events(id: string, options: { lastEventId?: string; signal?: AbortSignal } = {}): AsyncGenerator<JobEvent> {
    const headers = this.headers({ Accept: "text/event-stream",
      ...(options.lastEventId ? { "Last-Event-ID": options.lastEventId } : {}) });
    let response: Response;
    try {
      response = await this.fetchImpl(`${this.url}/v1/jobs/${seg(id)}/events`, { headers, signal: options.signal });
    } catch (e) {
      throw connectionError(`events: cannot reach ${this.url} (${(e as Error).message})`);
    }
    if (!response.ok || !response.body) throw await fromResponse(response);
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = "", kind = "message", data: string[] = [], lastId: string | undefined;
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return;
        buffer += value;
        let cut: number;
        while ((cut = buffer.indexOf("\n")) >= 0) {
          const line = buffer.slice(0, cut).replace(/\r$/, "");
          buffer = buffer.slice(cut + 1);
          if (line === "") {
            if (data.length) yield { event: kind, data: JSON.parse(data.join("\n")), id: lastId };
            kind = "message";
            data = [];
          } else if (!line.startsWith(":")) {
            const colon = line.indexOf(":");
            const name = colon < 0 ? line : line.slice(0, colon);
            const val = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
            if (name === "data") data.push(val);
            else if (name === "event") kind = val || "message";
            else if (name === "id") lastId = val;
          }
        }
      }
    } finally {
      reader.cancel().catch(() => undefined);
    }
  }

  /** Follow a job to its end by its events (reconnecting after the last one seen); the job as it ended. Throws a
   * FAILED_PRECONDITION error when it failed or was cancelled (unless `check` is false), DEADLINE_EXCEEDED after
   * `timeoutMs`. */
  async wait(id: string, options: { onEvent?: (e: JobEvent) => void; timeoutMs?: number; check?: boolean } = {}
  ): Promise<any> {
    const deadline = options.timeoutMs === undefined ? Infinity : Date.now() + options.timeoutMs;
    let lastEventId: string | undefined;
    let job: any;
    for (let failures = 0; ;) {
      job = await this.getJob(id);
      if (TERMINAL.has(job.state)) break;
      if (Date.now() > deadline) throw timeoutError(`job ${id} still ${job.state} after ${options.timeoutMs} ms`);
      const controller = new AbortController();
      const timer = setTimeout(() => controller.abort(), Math.min(60000, deadline - Date.now()));
      try {
        for await (const event of this.events(id, { lastEventId, signal: controller.signal })) {
          lastEventId = event.id ?? lastEventId;
          options.onEvent?.(event);
          if (event.event === "end" || (event.event === "state" && TERMINAL.has(event.data.state))) break;
        }
        failures = 0;
      } catch (e) {
        if (e instanceof BlendsplatError && !["UNAVAILABLE", "RESOURCE_EXHAUSTED"].includes(e.code)) throw e;
        failures += 1;
        await sleep(Math.min(5000, 500 * failures));
      } finally {
        clearTimeout(timer);
      }
    }
    if ((options.check ?? true) && job.state !== "succeeded") {
      throw new BlendsplatError({ code: "FAILED_PRECONDITION", message: `job ${id} ${job.state}`, field: "" });
    }
    return job;
  }

  // ------------------------------------------------------------------------------------------ streams
  /** A render stream over the WebSocket /v1/stream (the key as the `bearer.<key>` subprotocol). */
  stream(avatar: string, options: StreamOptions = {}): Promise<RenderStream> {
    if (!this.WS) throw new Error("no WebSocket here: pass one as the WebSocket option (Node 20: --experimental-websocket)");
    const ws = `${this.url.replace(/^http/, "ws")}/v1/stream`;
    return RenderStream.open(ws, this.apiKey, avatar, { timeoutMs: this.timeoutMs, ...options }, this.WS);
  }
}
