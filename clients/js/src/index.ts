// Blendsplat's TypeScript client: render streams (WebSocket), the REST API (avatars, adapters, uploads, training
// jobs with live events) and the WebRTC session. No framework; runs in browsers and Node 20+. The server ships this
// module compiled (service/static/client/, `npm run build:static`): its pages import /static/app/client/index.js.
export { Client, type CallOptions, type ClientOptions, type EventsOptions, type JobEvent, type RequestOptions,
  type RetryPolicy, type UploadOptions } from "./client.js";
export { BlendsplatError, type Status } from "./errors.js";
export { type Camera, type Pose } from "./pose.js";
export { randomId } from "./random.js";
export { SseParser, type SseEvent } from "./sse.js";
export { RenderStream, type Frame, type FinalStatus, type StreamHeader, type StreamOptions } from "./stream.js";
export { connectWebRTC, parseIceServers, type ShownFrame, type WebRTCOptions, type WebRTCSession,
  type WebRTCStats } from "./webrtc.js";
