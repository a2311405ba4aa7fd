// /static/app/webrtc.js: the WebRTC client's stable URL. Its code is the TypeScript client's (clients/js/src/webrtc.ts),
// shipped compiled in ./client/ (`npm run build:static` in clients/js); nothing else belongs here.
export { connectWebRTC, parseIceServers } from "./client/webrtc.js";
