// Poses in the driving-file vocabulary (docs/method.md section 11) -> FrameParams in protobuf's JSON mapping.
const flat = (m) => m.flat();
export function cameraJson(camera) {
    if (typeof camera === "string")
        return { preset: camera };
    if ("K" in camera) {
        return { opencv: { k: flat(camera.K), r: flat(camera.R ?? [1, 0, 0, 0, 1, 0, 0, 0, 1]), t: camera.t ?? [0, 0, 0],
                width: camera.width, height: camera.height } };
    }
    // only the fields given (protobuf's JSON leaves zeros out; an absent field is 0 to the server)
    const orbit = {};
    if (camera.yaw !== undefined)
        orbit.yawDeg = camera.yaw;
    if (camera.pitch !== undefined)
        orbit.pitchDeg = camera.pitch;
    if (camera.distance !== undefined)
        orbit.distance = camera.distance;
    return { orbit };
}
export function frameJson(index, pose) {
    const frame = { index: String(index), clientTimeUs: String(Date.now() * 1000) };
    if (Array.isArray(pose.expression))
        frame.coefficients = pose.expression;
    else if (pose.expression)
        frame.namedCoefficients = pose.expression;
    if (pose.joints) {
        frame.joints = Object.fromEntries(Object.entries(pose.joints).map(([name, values]) => [name, { values }]));
    }
    if (pose.eyelids)
        frame.eyelids = pose.eyelids;
    if (pose.camera !== undefined)
        frame.camera = cameraJson(pose.camera);
    if (pose.background)
        frame.background = { r: pose.background[0], g: pose.background[1], b: pose.background[2] };
    return frame;
}
export const CODECS = {
    jpeg: "CODEC_JPEG", png: "CODEC_PNG", raw: "CODEC_RAW_RGBA", h264: "CODEC_H264",
};
