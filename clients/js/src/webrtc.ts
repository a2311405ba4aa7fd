// The WebRTC session (WHEP-style signalling, a video track, poses on a data channel) is the server's own ES module,
// /static/app/webrtc.js, which the /demo page uses: re-exported here, loaded from the server it talks to, so the
// client and the server always speak the same version. Browsers only (RTCPeerConnection).

export interface WebRTCOptions {
  url?: string;
  avatar: string;
  size?: number;
  codecs?: string;
  apiKey?: string;
  video: HTMLVideoElement;
  onFrame?: (frame: { index: number; latencyMs: number }) => void;
  [option: string]: unknown;
}

export interface WebRTCSession {
  sendFrame(frame: Record<string, unknown>): void;
  close(): Promise<void>;
  [member: string]: unknown;
}

/** Connect a WebRTC session to the avatar (see service/static/webrtc.js for every option). */
export async function connectWebRTC(options: WebRTCOptions): Promise<WebRTCSession> {
  const base = (options.url ?? (globalThis as any).location?.origin ?? "").replace(/\/+$/, "");
  const module = await import(/* @vite-ignore */ `${base}/static/app/webrtc.js`);
  return module.connectWebRTC({ ...options, url: base });
}
