// Blendsplat's TypeScript client: render streams (WebSocket), the REST API (avatars, adapters, uploads, training
// jobs with live events) and the WebRTC session. No framework; runs in browsers and Node 20+.
export { Client, type ClientOptions, type JobEvent, type RetryPolicy } from "./client.js";
export { BlendsplatError, type Status } from "./errors.js";
export { type Camera, type Pose } from "./pose.js";
export { RenderStream, type Frame, type FinalStatus, type StreamHeader, type StreamOptions } from "./stream.js";
export { connectWebRTC, type WebRTCOptions, type WebRTCSession } from "./webrtc.js";
