// The REST API (avatars, adapters, uploads, training jobs with live events) and render streams, with retries of
// idempotent calls (GET, PUT, DELETE; POST /v1/jobs with an Idempotency-Key) on 408, 429, 5xx and network
// failures, with backoff and jitter, honouring Retry-After; a timeout on every call.

import { BlendsplatError, connectionError, fromResponse, timeoutError } from "./errors.js";
import { randomId } from "./random.js";
import { SseParser } from "./sse.js";
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

/** A server-sent event of a job: its type, its data (parsed JSON; null when the data is not JSON: `text` holds it)
 * and the last event id seen (what a reconnect sends as Last-Event-ID). */
export interface JobEvent { event: string; data: Record<string, any> | null; text: string; id?: string }

/** Options of any one call: `signal` aborts it (the promise rejects with the signal's reason, an AbortError). */
export interface CallOptions { signal?: AbortSignal; timeoutMs?: number }

export interface RequestOptions extends CallOptions {
  query?: Record<string, string | number | undefined>;
  json?: unknown;
  body?: () => BodyInit;
  headers?: Record<string, string>;
  read?: "json" | "bytes" | "blob" | "none";
}

export interface UploadOptions extends CallOptions {
  filename?: string;
  /** bytes of the file sent so far, and its size (in a browser through XMLHttpRequest's upload events) */
  onProgress?: (sent: number, total: number) => void;
}

export interface EventsOptions {
  lastEventId?: string;
  signal?: AbortSignal;
  /** called once the server accepted the request (a text/event-stream answer), before any event */
  onOpen?: () => void;
  /** the reconnection time a `retry:` field asks for, in ms */
  onRetry?: (ms: number) => void;
}

const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);
const IDEMPOTENT = new Set(["GET", "HEAD", "PUT", "DELETE"]);
const seg = (id: string) => encodeURIComponent(id);

function aborted(signal?: AbortSignal): unknown {
  return signal?.reason ?? new DOMException("aborted", "AbortError");
}

/** Wait `ms`, or until `signal` aborts (then reject with its reason). */
function sleep(ms: number, signal?: AbortSignal): Promise<void> {
  return new Promise((resolve, reject) => {
    if (signal?.aborted) return reject(aborted(signal));
    const stop = () => { clearTimeout(timer); reject(aborted(signal)); };
    const timer = setTimeout(() => { signal?.removeEventListener("abort", stop); resolve(); }, ms);
    signal?.addEventListener("abort", stop, { once: true });
  });
}

export class Client {
  readonly url: string;
  readonly timeoutMs: number;
  readonly retry: RetryPolicy;
  private readonly apiKey?: string;
  private readonly fetchImpl: typeof fetch;
  private readonly ownFetch: boolean; // a fetch was passed: every call goes through it
  private readonly WS?: typeof WebSocket;

  constructor(options: ClientOptions = {}) {
    const origin = (globalThis as any).location?.origin as string | undefined;
    this.url = (options.url ?? origin ?? "http://127.0.0.1:8080").replace(/\/+$/, "");
    this.apiKey = options.apiKey;
    this.timeoutMs = options.timeoutMs ?? 30000;
    this.retry = { attempts: 4, backoffMs: 250, maxBackoffMs: 8000, maxRetryAfterMs: 60000, ...options.retry };
    this.fetchImpl = options.fetch ?? globalThis.fetch.bind(globalThis);
    this.ownFetch = options.fetch !== undefined;
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

  /** One API call with the client's key, timeout and retries; the JSON answer (or bytes, a Blob, or nothing).
   * `path` is a path of this server, e.g. a link a job's answer carries. */
  async request(method: string, path: string, options: RequestOptions = {}): Promise<any> {
    const headers = this.headers(options.headers);
    const idempotent = IDEMPOTENT.has(method) || (method === "POST" && path === "/v1/jobs" && "Idempotency-Key" in headers);
    const query = Object.entries(options.query ?? {}).filter(([, v]) => v !== undefined)
      .map(([k, v]) => `${encodeURIComponent(k)}=${encodeURIComponent(String(v))}`).join("&");
    const url = `${this.url}${path}${query ? `?${query}` : ""}`;
    const outer = options.signal;
    for (let attempt = 0; ; attempt++) {
      if (outer?.aborted) throw aborted(outer);
      let error: BlendsplatError;
      const controller = new AbortController();
      const timer = setTimeout(() => controller.abort(), options.timeoutMs ?? this.timeoutMs);
      const abort = () => controller.abort();
      outer?.addEventListener("abort", abort, { once: true });
      try {
        const body = options.json !== undefined ? JSON.stringify(options.json) : options.body?.();
        if (options.json !== undefined) headers["Content-Type"] = "application/json";
        const response = await this.fetchImpl(url, { method, headers, body, signal: controller.signal,
          ...(body instanceof ReadableStream ? { duplex: "half" } : {}) } as RequestInit);
        if (response.ok) {
          if (options.read === "none" || response.status === 204) return null;
          if (options.read === "bytes") return new Uint8Array(await response.arrayBuffer());
          if (options.read === "blob") return await response.blob();
          return await response.json();
        }
        error = await fromResponse(response);
      } catch (e) {
        if (e instanceof BlendsplatError) throw e;
        if (outer?.aborted) throw aborted(outer);
        if (controller.signal.aborted) throw timeoutError(`${method} ${path}: no answer in time`);
        error = connectionError(`${method} ${path}: cannot reach ${this.url} (${(e as Error).message})`);
      } finally {
        clearTimeout(timer);
        outer?.removeEventListener("abort", abort);
      }
      const wait = this.delay(attempt, error, idempotent);
      if (wait === null) throw error;
      await sleep(wait, outer);
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
   * as the body goes (in a browser through XMLHttpRequest, whose upload events count what the network took).
   * Not retried (not idempotent). */
  upload(file: Blob | Uint8Array, options: UploadOptions = {}): Promise<any> {
    const blob = file instanceof Blob ? file : new Blob([file as BlobPart]);
    const name = (options.filename ?? (file as File).name ?? "upload").replace(/["\r\n]/g, "_");
    const XHR = (globalThis as any).XMLHttpRequest as typeof XMLHttpRequest | undefined;
    if (options.onProgress && XHR && !this.ownFetch) {
      return this.uploadXhr(XHR, blob, name, options);
    }
    const boundary = randomId("blendsplat-");
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
      signal: options.signal, headers: { "Content-Type": `multipart/form-data; boundary=${boundary}` } });
  }

  // A browser's fetch cannot stream a request body over HTTP/1.1 (nor report its progress): XMLHttpRequest can.
  private uploadXhr(XHR: typeof XMLHttpRequest, blob: Blob, name: string, options: UploadOptions): Promise<any> {
    const progress = options.onProgress!;
    return new Promise((resolve, reject) => {
      const xhr = new XHR();
      const signal = options.signal;
      const stop = () => xhr.abort();
      const done = () => signal?.removeEventListener("abort", stop);
      if (signal?.aborted) return reject(aborted(signal));
      signal?.addEventListener("abort", stop, { once: true });
      xhr.open("POST", `${this.url}/v1/uploads`);
      for (const [k, v] of Object.entries(this.headers())) xhr.setRequestHeader(k, v);
      xhr.timeout = options.timeoutMs ?? 600000;
      xhr.upload.onprogress = (ev) => {
        if (ev.lengthComputable) progress(Math.min(ev.loaded, blob.size), blob.size);
      };
      xhr.upload.onload = () => progress(blob.size, blob.size);
      xhr.onload = async () => {
        done();
        if (xhr.status >= 200 && xhr.status < 300) {
          try { resolve(JSON.parse(xhr.responseText)); } catch (e) {
            reject(connectionError(`POST /v1/uploads: the answer is not JSON (${(e as Error).message})`));
          }
          return;
        }
        const headers = new Headers();
        const wait = xhr.getResponseHeader("Retry-After");
        if (wait) headers.set("Retry-After", wait);
        try {
          reject(await fromResponse(new Response(xhr.responseText, { status: xhr.status, headers })));
        } catch { // a status a Response cannot carry (1xx, a body with 204 or 304)
          reject(connectionError(`POST /v1/uploads: unexpected HTTP ${xhr.status}`));
        }
      };
      xhr.onerror = () => { done(); reject(connectionError(`POST /v1/uploads: cannot reach ${this.url}`)); };
      xhr.ontimeout = () => { done(); reject(timeoutError("POST /v1/uploads: no answer in time")); };
      xhr.onabort = () => { done(); reject(aborted(signal)); };
      const form = new FormData();
      form.append("file", blob, name);
      xhr.send(form);
    });
  }
  async listUploads(): Promise<any[]> { return (await this.request("GET", "/v1/uploads")).uploads; }
  getUpload(id: string): Promise<any> { return this.request("GET", `/v1/uploads/${seg(id)}`); }
  deleteUpload(id: string): Promise<null> { return this.request("DELETE", `/v1/uploads/${seg(id)}`, { read: "none" }); }

  // ------------------------------------------------------------------------------------------ jobs
  /** POST /v1/jobs with an Idempotency-Key (a fresh one unless given; null: none), so a retry makes no second job. */
  submitJob(spec: Record<string, unknown> & { upload_id: string }, idempotencyKey: string | null = randomId()
  ): Promise<any> {
    return this.request("POST", "/v1/jobs", { json: spec,
      headers: idempotencyKey ? { "Idempotency-Key": idempotencyKey } : {} });
  }
  getJob(id: string, options: CallOptions = {}): Promise<any> {
    return this.request("GET", `/v1/jobs/${seg(id)}`, options);
  }
  cancelJob(id: string): Promise<any> { return this.request("POST", `/v1/jobs/${seg(id)}/cancel`); }
  deleteJob(id: string): Promise<null> { return this.request("DELETE", `/v1/jobs/${seg(id)}`, { read: "none" }); }
  artefact(id: string, name: string, options: CallOptions = {}): Promise<Uint8Array> {
    return this.request("GET", `/v1/jobs/${seg(id)}/artefacts/${seg(name)}`, { ...options, read: "bytes" });
  }
  /** GET a path of this server as a Blob (typed by its Content-Type): e.g. a link of a job's `links.artefacts`,
   * for an <img> (an <img src> cannot send the key) or a download. */
  blob(path: string, options: CallOptions = {}): Promise<Blob> {
    return this.request("GET", path, { ...options, read: "blob", headers: { Accept: "*/*" } });
  }

  /** One page of GET /v1/jobs, newest first: {jobs, next_cursor}. */
  listJobs(options: { state?: string; limit?: number; cursor?: string } & CallOptions = {}): Promise<any> {
    const { state, limit, cursor, ...call } = options;
    return this.request("GET", "/v1/jobs", { ...call, query: { state, limit, cursor } });
  }

  /** Every job, newest first, page after page (GET /v1/jobs cursors). */
  async *jobs(options: { state?: string; pageSize?: number } = {}): AsyncGenerator<any> {
    let cursor: string | undefined;
    do {
      const page = await this.listJobs({ state: options.state, limit: options.pageSize ?? 50, cursor });
      yield* page.jobs;
      cursor = page.next_cursor ?? undefined;
    } while (cursor);
  }

  /** GET /v1/jobs/{id}/events: the job's server-sent events (after `lastEventId`) until the server closes (read
   * with fetch: EventSource cannot send an Authorization header). A refused request throws its typed error (a
   * server without the route: NOT_FOUND, httpStatus 404), an answer that is not text/event-stream an UNIMPLEMENTED
   * one; `signal` ends it (an AbortError). */
  async *events(id: string, options: EventsOptions = {}): AsyncGenerator<JobEvent> {
    const headers = this.headers({ Accept: "text/event-stream",
      ...(options.lastEventId ? { "Last-Event-ID": options.lastEventId } : {}) });
    let response: Response;
    try {
      response = await this.fetchImpl(`${this.url}/v1/jobs/${seg(id)}/events`,
        { headers, signal: options.signal, cache: "no-store" });
    } catch (e) {
      if (options.signal?.aborted) throw aborted(options.signal);
      throw connectionError(`events: cannot reach ${this.url} (${(e as Error).message})`);
    }
    if (!response.ok || !response.body) throw await fromResponse(response);
    const type = (response.headers.get("content-type") ?? "").toLowerCase();
    if (!type.startsWith("text/event-stream")) {
      response.body.cancel().catch(() => undefined);
      throw new BlendsplatError({ code: "UNIMPLEMENTED", field: "",
        message: `the events answer is ${type || "untyped"}, not text/event-stream` }, response.status);
    }
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    options.onOpen?.();
    const parser = new SseParser(options.lastEventId);
    let retry = parser.retryMs;
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return;
        for (const e of parser.feed(value)) {
          let data: Record<string, any> | null = null;
          try {
            const parsed = JSON.parse(e.data);
            data = parsed !== null && typeof parsed === "object" ? parsed : { value: parsed };
          } catch { /* not JSON: `text` has it */ }
          yield { event: e.event, data, text: e.data, id: e.id };
        }
        if (parser.retryMs !== retry) options.onRetry?.((retry = parser.retryMs)!);
      }
    } catch (e) {
      if (options.signal?.aborted) throw aborted(options.signal);
      throw e instanceof BlendsplatError ? e : connectionError(`events: the stream broke (${(e as Error).message})`);
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
          if (event.event === "end" || (event.event === "state" && TERMINAL.has(event.data?.state))) break;
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
