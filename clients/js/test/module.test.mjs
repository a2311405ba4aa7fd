// The module's pieces that need no Blendsplat server (compiled: dist/): the server-sent events parser, the WHEP
// Link header parser, random ids, poses, and the client's events reader, aborts and Blob reads against a small
// scripted node:http server.
import assert from "node:assert/strict";
import { createServer } from "node:http";
import { after, before, test } from "node:test";

import { BlendsplatError, Client, SseParser, parseIceServers, randomId } from "../dist/index.js";
import { frameJson } from "../dist/pose.js";

test("SseParser: CR, LF and CRLF lines, split anywhere; comments, retry, ids kept across events", () => {
  const text = "retry: 300\n: a comment\n\nid: 1\nevent: progress\ndata: {\"i\":1}\r\n\r\n" +
    "data: a\rdata: b\r\rid: 2\nevent: state\ndata:{\"state\":\"running\"}\r\n\r\ndata: no id\n\nid: x\0y\ndata: z\n\n";
  const whole = new SseParser().feed(text);
  assert.deepEqual(whole, [
    { event: "progress", data: "{\"i\":1}", id: "1" },
    { event: "message", data: "a\nb", id: "1" },
    { event: "state", data: "{\"state\":\"running\"}", id: "2" },
    { event: "message", data: "no id", id: "2" },
    { event: "message", data: "z", id: "2" }, // an id with a NUL is ignored
  ]);
  for (const size of [1, 2, 3, 7, 37]) { // every way of cutting it, CRLF split across chunks included
    const parser = new SseParser();
    const events = [];
    for (let i = 0; i < text.length; i += size) events.push(...parser.feed(text.slice(i, i + size)));
    assert.deepEqual(events, whole, `chunks of ${size}`);
    assert.equal(parser.retryMs, 300);
    assert.equal(parser.lastEventId, "2");
  }
  const resumed = new SseParser("41");
  assert.deepEqual(resumed.feed("data: 1\n\nevent: end\n\n"), [{ event: "message", data: "1", id: "41" }]);
  assert.equal(resumed.feed("data: unfinished\n").length, 0); // not dispatched without its blank line
});

test("parseIceServers: WHEP Link values, joined by fetch or one per item; other links left out", () => {
  const turn = '<turn:turn.example:3478?transport=udp>; rel="ice-server"; username="1700000000:blendsplat"; ' +
    'credential="a+b/c=="; credential-type="password"';
  const joined = `<stun:stun.example:3478>; rel="ice-server", <https://x.example/doc>; rel="help", ${turn}, ` +
    '<turns:t.example:443?transport=tcp>;rel=ice-server;username=u;credential="q\\"uote"';
  const expected = [
    { urls: "stun:stun.example:3478" },
    { urls: "turn:turn.example:3478?transport=udp", username: "1700000000:blendsplat", credential: "a+b/c==" },
    { urls: "turns:t.example:443?transport=tcp", username: "u", credential: 'q"uote' },
  ];
  assert.deepEqual(parseIceServers(joined), expected);
  assert.deepEqual(parseIceServers(joined.split(/, (?=<)/)), expected);
  assert.deepEqual(parseIceServers(null), []);
  assert.deepEqual(parseIceServers("garbage <without end"), []);
});

test("randomId: unique hex ids, without crypto.randomUUID too", () => {
  const a = randomId("k-"), b = randomId("k-");
  assert.match(a, /^k-[0-9a-f-]{32,36}$/);
  assert.notEqual(a, b);
  const saved = Object.getOwnPropertyDescriptor(globalThis.crypto, "randomUUID");
  Object.defineProperty(globalThis.crypto, "randomUUID", { value: undefined, configurable: true });
  try {
    assert.match(randomId(), /^[0-9a-f]{32}$/); // crypto.getRandomValues: what a page on plain http has
  } finally {
    if (saved) Object.defineProperty(globalThis.crypto, "randomUUID", saved);
    else delete globalThis.crypto.randomUUID;
  }
});

test("poses: an orbit camera carries only the fields given", () => {
  assert.deepEqual(frameJson(3, { camera: { yaw: 0 } }).camera, { orbit: { yawDeg: 0 } });
  assert.deepEqual(frameJson(3, { camera: { yaw: 5, pitch: 1, distance: 2 } }).camera,
    { orbit: { yawDeg: 5, pitchDeg: 1, distance: 2 } });
  const f = frameJson(4, { expression: { jawOpen: 0.4 }, joints: { jaw: [0.1, 0, 0] } });
  assert.deepEqual([f.index, f.namedCoefficients, f.joints], ["4", { jawOpen: 0.4 }, { jaw: { values: [0.1, 0, 0] } }]);
});

// ---------------------------------------------------------------------------------- a scripted events server
let server, url;
const seen = [];

before(async () => {
  server = createServer((req, res) => {
    seen.push({ path: req.url, auth: req.headers.authorization, last: req.headers["last-event-id"] });
    if (req.url === "/v1/jobs/job_a/events") {
      res.writeHead(200, { "Content-Type": "text/event-stream; charset=utf-8" });
      const after = Number(req.headers["last-event-id"] ?? 0);
      const body = "retry: 250\n\n" + [1, 2, 3].filter((n) => n > after)
        .map((n) => `id: ${n}\r\nevent: progress\r\ndata: {"iteration": ${n}}\r\n\r\n`).join("") +
        "event: log\ndata: not json\n\n";
      let i = 0;
      const step = () => { // in pieces of 5 bytes that split lines and CRLFs
        if (i >= body.length) return res.end();
        res.write(body.slice(i, (i += 5)));
        setTimeout(step, 1);
      };
      step();
    } else if (req.url === "/v1/jobs/job_json/events") {
      res.writeHead(200, { "Content-Type": "application/json" });
      res.end("{}");
    } else if (req.url === "/v1/jobs/job_slow/events") {
      res.writeHead(200, { "Content-Type": "text/event-stream" });
      res.write("data: {\"first\": true}\n\n"); // then nothing: the reader waits until aborted
    } else if (req.url === "/slow") {
      setTimeout(() => res.end("{}"), 2000);
    } else if (req.url === "/v1/jobs/job_a/artefacts/preview") {
      res.writeHead(200, { "Content-Type": "image/png" });
      res.end(Buffer.from([0x89, 0x50, 0x4e, 0x47]));
    } else {
      res.writeHead(404, { "Content-Type": "application/json" });
      res.end(JSON.stringify({ error: { code: "NOT_FOUND", message: `no ${req.url}`, field: "" } }));
    }
  });
  await new Promise((done) => server.listen(0, "127.0.0.1", done));
  url = `http://127.0.0.1:${server.address().port}`;
});
after(() => { server.closeAllConnections(); server.close(); });

test("events: parsed in pieces with the key, non-JSON data kept as text, retry reported, resumed by id", async () => {
  const client = new Client({ url, apiKey: "k1" });
  const retries = [];
  const events = [];
  let opened = 0;
  for await (const e of client.events("job_a", { onRetry: (ms) => retries.push(ms), onOpen: () => opened++ })) {
    events.push(e);
  }
  assert.equal(opened, 1);
  assert.deepEqual(events.map((e) => [e.event, e.data?.iteration ?? null, e.id]),
    [["progress", 1, "1"], ["progress", 2, "2"], ["progress", 3, "3"], ["log", null, "3"]]);
  assert.equal(events[3].text, "not json");
  assert.deepEqual(retries, [250]);
  const resumed = [];
  for await (const e of client.events("job_a", { lastEventId: "2" })) resumed.push(e.id);
  assert.deepEqual(resumed, ["3", "3"]);
  assert.deepEqual(seen.filter((s) => s.path.endsWith("/events")).map((s) => [s.auth, s.last ?? null]),
    [["Bearer k1", null], ["Bearer k1", "2"]]);
});

test("events: a missing route is a typed 404, a wrong content type UNIMPLEMENTED, an abort an AbortError", async () => {
  const client = new Client({ url });
  const drain = async (gen) => { for await (const _ of gen) { /* read all */ } };
  await assert.rejects(drain(client.events("job_none")), (e) => e instanceof BlendsplatError && e.code === "NOT_FOUND"
    && e.httpStatus === 404);
  await assert.rejects(drain(client.events("job_json")), (e) => e.code === "UNIMPLEMENTED" && e.httpStatus === 200
    && /application\/json, not text\/event-stream/.test(e.message));
  const controller = new AbortController();
  const got = [];
  const reading = (async () => {
    for await (const e of client.events("job_slow", { signal: controller.signal })) {
      got.push(e.data);
      controller.abort();
    }
  })();
  await assert.rejects(reading, (e) => e.name === "AbortError");
  assert.deepEqual(got, [{ first: true }]);
});

test("calls: an aborted request rejects with AbortError (not a timeout); blob() keeps the content type", async () => {
  const client = new Client({ url, timeoutMs: 10000 });
  const controller = new AbortController();
  setTimeout(() => controller.abort(), 100);
  const t0 = Date.now();
  await assert.rejects(client.request("GET", "/slow", { signal: controller.signal }), (e) => e.name === "AbortError");
  assert.ok(Date.now() - t0 < 3000);
  const blob = await client.blob("/v1/jobs/job_a/artefacts/preview");
  assert.equal(blob.type, "image/png");
  assert.deepEqual([...new Uint8Array(await blob.arrayBuffer())], [0x89, 0x50, 0x4e, 0x47]);
  await assert.rejects(client.blob("/v1/jobs/job_a/artefacts/none"), (e) => e.code === "NOT_FOUND"
    && e.status.message === "no /v1/jobs/job_a/artefacts/none");
});
