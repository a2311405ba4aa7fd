// Poses in the driving-file vocabulary (docs/method.md section 11) -> FrameParams in protobuf's JSON mapping.

export type Camera = string | { yaw?: number; pitch?: number; distance?: number }
  | { K: number[] | number[][]; R?: number[] | number[][]; t?: number[]; width: number; height: number };

export interface Pose {
  /** K coefficients in the avatar's order, or {name: value} (any subset, the rest zero) */
  expression?: number[] | Record<string, number>;
  /** joint name -> 3 axis-angle or 6 (6D) values */
  joints?: Record<string, number[]>;
  eyelids?: [number, number];
  camera?: Camera;
  background?: [number, number, number];
}

const flat = (m: number[] | number[][]): number[] => (m as (number | number[])[]).flat() as number[];

export function cameraJson(camera: Camera): Record<string, unknown> {
  if (typeof camera === "string") return { preset: camera };
  if ("K" in camera) {
    return { opencv: { k: flat(camera.K), r: flat(camera.R ?? [1, 0, 0, 0, 1, 0, 0, 0, 1]), t: camera.t ?? [0, 0, 0],
      width: camera.width, height: camera.height } };
  }
  // only the fields given (protobuf's JSON leaves zeros out; an absent field is 0 to the server)
  const orbit: Record<string, number> = {};
  if (camera.yaw !== undefined) orbit.yawDeg = camera.yaw;
  if (camera.pitch !== undefined) orbit.pitchDeg = camera.pitch;
  if (camera.distance !== undefined) orbit.distance = camera.distance;
  return { orbit };
}

export function frameJson(index: number, pose: Pose): Record<string, unknown> {
  const frame: Record<string, unknown> = { index: String(index), clientTimeUs: String(Date.now() * 1000) };
  if (Array.isArray(pose.expression)) frame.coefficients = pose.expression;
  else if (pose.expression) frame.namedCoefficients = pose.expression;
  if (pose.joints) {
    frame.joints = Object.fromEntries(Object.entries(pose.joints).map(([name, values]) => [name, { values }]));
  }
  if (pose.eyelids) frame.eyelids = pose.eyelids;
  if (pose.camera !== undefined) frame.camera = cameraJson(pose.camera);
  if (pose.background) frame.background = { r: pose.background[0], g: pose.background[1], b: pose.background[2] };
  return frame;
}

export const CODECS: Record<string, string> = {
  jpeg: "CODEC_JPEG", png: "CODEC_PNG", raw: "CODEC_RAW_RGBA", h264: "CODEC_H264",
};
