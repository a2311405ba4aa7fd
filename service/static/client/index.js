// Blendsplat's TypeScript client: render streams (WebSocket), the REST API (avatars, adapters, uploads, training
// jobs with live events) and the WebRTC session. No framework; runs in browsers and Node 20+. The server ships this
// module compiled (service/static/client/, `npm run build:static`): its pages import /static/app/client/index.js.
export { Client } from "./client.js";
export { BlendsplatError } from "./errors.js";
export { randomId } from "./random.js";
export { SseParser } from "./sse.js";
export { RenderStream } from "./stream.js";
export { connectWebRTC, parseIceServers } from "./webrtc.js";
