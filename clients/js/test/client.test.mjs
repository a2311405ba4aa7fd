// The TypeScript client (compiled: dist/) against a real server: every call's happy path, typed errors, retries
// of idempotent calls on an injected 503 and none of a non-idempotent one, timeouts.
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { createServer } from "node:net";
import { join } from "node:path";
import { after, before, test } from "node:test";

import { BlendsplatError, Client } from "../dist/index.js";
import { DATA, startServer } from "./support/server.mjs";

let server, client;
const poses = readFileSync(join(DATA, "drive.jsonl"), "utf8").split("\n").filter(Boolean).map((l) => JSON.parse(l));
const FAST = { attempts: 4, backoffMs: 20, maxBackoffMs: 200 };

before(async () => {
  server = await startServer();
  client = new Client({ url: server.url, apiKey: server.key, retry: FAST });
});
after(async () => server && (await server.stop()));

/** fetch that answers the first `n` requests matching `match` with `status` itself; records every request. */
function flaky(match, n = 1, status = 503, headers = {}) {
  const seen = [];
  const impl = async (url, init = {}) => {
    seen.push(`${init.method ?? "GET"} ${new URL(url).pathname}`);
    if (n > 0 && match(url, init)) {
      n -= 1;
      return new Response(JSON.stringify({ error: { code: "UNAVAILABLE", message: "injected", field: "" } }),
        { status, headers: { "Content-Type": "application/json", ...headers } });
    }
    return fetch(url, init);
  };
  return { impl, seen };
}

test("avatars: list, get, typed NOT_FOUND with its field", async () => {
  const avatars = await client.listAvatars();
  assert.ok(avatars.some((a) => a.id === "demo"));
  assert.equal((await client.getAvatar("demo")).id, "demo");
  await assert.rejects(client.getAvatar("no-such"), (e) => e instanceof BlendsplatError && e.code === "NOT_FOUND"
    && e.field === "avatar_id" && e.httpStatus === 404);
  assert.ok(Array.isArray(await client.listAdapters()));
});

test("a WebSocket stream: header, frames with latency, lockstep render, errors that keep the stream", async () => {
  const s = await client.stream("demo", { size: 64, codec: "jpeg" });
  try {
    assert.equal(s.header.width, 64);
    assert.ok(s.header.expressionNames.includes("jawOpen"));
    assert.equal(s.send({ expression: { jawOpen: 0.5 }, joints: { jaw: [0.1, 0, 0] }, camera: "front" }), 1);
    const frame = await s.receive();
    assert.equal(frame.index, 1);
    assert.deepEqual([...frame.data.slice(0, 2)], [0xff, 0xd8]); // JPEG
    assert.ok(frame.latencyMs > 0 && frame.timings.total > 0);
    const indices = [];
    for await (const f of s.render(poses.slice(0, 4))) indices.push(f.index);
    assert.deepEqual(indices, [2, 3, 4, 5]);
    s.send({ expression: { noSuchName: 1 } });
    await assert.rejects(s.receive(), (e) => e.code === "INVALID_ARGUMENT" && e.field === "named_coefficients");
    s.send({ camera: { yaw: 10 } });
    assert.equal((await s.receive()).index, 7);
    await assert.rejects(s.receive(200), (e) => e.code === "DEADLINE_EXCEEDED");
    assert.deepEqual(await s.end(), []);
    assert.equal(s.final.framesSent, 6);
  } finally {
    s.close();
  }
  await assert.rejects(client.stream("no-such"), (e) => e.code === "NOT_FOUND" && e.field === "avatar_id");
  const bad = new Client({ url: server.url, apiKey: "bsk_wrong" });
  await assert.rejects(bad.stream("demo"), (e) => e.code === "UNAUTHENTICATED");
});

test("idempotent calls are retried on 503 honouring Retry-After; a POST is not", async () => {
  const f = flaky((url, init) => (init.method ?? "GET") === "GET", 1, 503, { "Retry-After": "1" });
  const c = new Client({ url: server.url, apiKey: server.key, retry: FAST, fetch: f.impl });
  const t0 = Date.now();
  assert.ok((await c.listAvatars()).length > 0);
  assert.ok(Date.now() - t0 >= 1000);
  assert.deepEqual(f.seen, ["GET /v1/avatars", "GET /v1/avatars"]);
  const p = flaky((url, init) => init.method === "POST", 2);
  const c2 = new Client({ url: server.url, apiKey: server.key, retry: FAST, fetch: p.impl });
  await assert.rejects(c2.upload(new Uint8Array([1, 2, 3])), (e) => e.code === "UNAVAILABLE" && e.httpStatus === 503);
  await assert.rejects(c2.submitJob({ upload_id: "upl_x", avatar_id: "x" }, null), (e) => e.code === "UNAVAILABLE");
  assert.deepEqual(p.seen, ["POST /v1/uploads", "POST /v1/jobs"]);
});

test("a call past its timeout is DEADLINE_EXCEEDED", async () => {
  const silent = createServer(() => {}); // accepts, never answers
  await new Promise((done) => silent.listen(0, "127.0.0.1", done));
  try {
    const c = new Client({ url: `http://127.0.0.1:${silent.address().port}`, timeoutMs: 300, retry: FAST });
    await assert.rejects(c.getJob("job_x"), (e) => e.code === "DEADLINE_EXCEEDED");
  } finally {
    silent.close();
  }
});

test("jobs: upload with progress, submit (retried once with its key), follow events, artefact, pages, cancel, delete",
  async () => {
    const archive = readFileSync(join(DATA, "dataset.tar.gz"));
    const progress = [];
    const upload = await client.upload(new Blob([archive]), { filename: "dataset.tar.gz",
      onProgress: (sent, total) => progress.push([sent, total]) });
    assert.equal(upload.kind, "dataset");
    assert.deepEqual(progress.at(-1), [archive.length, archive.length]);
    const f = flaky((url, init) => init.method === "POST" && new URL(url).pathname === "/v1/jobs");
    const retrying = new Client({ url: server.url, apiKey: server.key, retry: FAST, fetch: f.impl });
    const job = await retrying.submitJob({ upload_id: upload.upload_id, preset: "tiny", iterations: 5,
      avatar_id: "js-client-job" });
    assert.deepEqual(f.seen, ["POST /v1/jobs", "POST /v1/jobs"]);
    const events = [];
    const done = await client.wait(job.id, { onEvent: (e) => events.push(e), timeoutMs: 600000 });
    assert.equal(done.state, "succeeded");
    assert.ok(events.some((e) => e.event === "progress" && e.data.iteration === 5));
    const report = JSON.parse(new TextDecoder().decode(await client.artefact(job.id, "report")));
    assert.equal(typeof report, "object");
    const second = await client.submitJob({ upload_id: upload.upload_id, iterations: 5000, avatar_id: "js-client-2" });
    const ids = [];
    for await (const j of client.jobs({ pageSize: 1 })) ids.push(j.id);
    assert.deepEqual(ids.slice(0, 2), [second.id, job.id]);
    await client.cancelJob(second.id);
    await assert.rejects(client.wait(second.id, { timeoutMs: 120000 }), (e) => e.code === "FAILED_PRECONDITION");
    assert.equal(await client.deleteJob(second.id), null);
    await assert.rejects(client.getJob(second.id), (e) => e.code === "NOT_FOUND");
    await assert.rejects(client.submitJob({ upload_id: upload.upload_id, iterations: -1, avatar_id: "x" }),
      (e) => e.code === "INVALID_ARGUMENT" && e.field === "iterations");
    assert.ok((await client.listUploads()).some((u) => u.upload_id === upload.upload_id));
  });
