"""Dense face landmarks (MediaPipe's face mesh: 468 points) and irises (5 points per eye), with our own crops.

Face mesh: the face's region is a square rotated so that the eyes lie level: from a detection, the box scaled 1.5x
(square on its long side) at the angle of the line from the right-eye keypoint to the left-eye one; from the
previous frame's landmarks (tracking), the landmarks' extent at the angle of the line through the outer eye corners
(landmarks 33 and 263), also scaled 1.5x. The model sees that square at 192x192, RGB in [0, 1]; it returns 468
(x, y, z) in the crop's pixels (z: depth relative to the face's centre, same scale as x; smaller = nearer the camera)
and a face-presence logit (a face: sigmoid > 0.5).

Irises: each eye's region is a square of 2.3x the distance between its corners (33-133 for the subject's right eye,
362-263 for the left), centred between them, level with the corners; the model wants the eye with its outer corner
on the crop's left, so the left eye's crop is mirrored. It sees 64x64, RGB in [0, 1]; it returns 71 eye-contour
points and 5 iris points (the centre, then four on the iris's edge), (x, y, z) in the crop's pixels. Both are mapped
back to image pixels (z scaled like x) by :meth:`~.geometry.Rect.to_image`.
"""

from __future__ import annotations

import math

import numpy as np

from .detect import Detection
from .geometry import Rect, crop, rect_from_points
from .runner import load_model

MESH_SIZE, IRIS_SIZE = 192, 64
FACE_SCALE, EYE_SCALE = 1.5, 2.3
PRESENCE = 0.5
OUTER_EYE_CORNERS = (33, 263)  # the subject's right and left outer eye corners
EYE_CORNERS = {"right": (33, 133), "left": (263, 362)}  # (outer, inner)
# Well-defined points of the canonical face mesh (MediaPipe's indices, subject's left/right)
POINTS = {"right_eye_outer": 33, "right_eye_inner": 133, "left_eye_inner": 362, "left_eye_outer": 263,
          "nose_tip": 1, "mouth_right": 61, "mouth_left": 291, "upper_lip": 13, "lower_lip": 14, "chin": 152}


def roi_from_detection(d: Detection) -> Rect:
    """The face-mesh crop for a detection."""
    (x0, y0), (x1, y1) = d.keypoints[0], d.keypoints[1]
    angle = math.atan2(y1 - y0, x1 - x0)
    box = d.box
    rect = Rect((box[0] + box[2]) / 2, (box[1] + box[3]) / 2, box[2] - box[0], box[3] - box[1], angle)
    return rect.scaled(FACE_SCALE, square_long=True)


def eye_angle(landmarks: np.ndarray) -> float:
    """The roll of the face: the angle of the line from the right outer eye corner to the left one."""
    a, b = landmarks[OUTER_EYE_CORNERS[0], :2], landmarks[OUTER_EYE_CORNERS[1], :2]
    return math.atan2(b[1] - a[1], b[0] - a[0])


def roi_from_landmarks(landmarks: np.ndarray) -> Rect:
    """The face-mesh crop for the next frame, from this frame's landmarks ``[468, 3]``."""
    return rect_from_points(landmarks[:, :2], eye_angle(landmarks), FACE_SCALE)


def face_mesh(rgb: np.ndarray, rect: Rect) -> tuple[np.ndarray, float]:
    """(landmarks ``[468, 3]`` in image pixels, face-presence probability) in the crop ``rect`` of ``rgb``."""
    x = crop(rgb, rect, MESH_SIZE, MESH_SIZE) * (1.0 / 255.0)
    points, logit = _mesh_outputs(load_model("face_landmark")(x[None]))
    return _to_image(points, rect, MESH_SIZE), 1.0 / (1.0 + math.exp(-float(np.clip(logit, -100.0, 100.0))))


def eye_rois(landmarks: np.ndarray) -> dict[str, Rect]:
    """The iris model's crops of both eyes (``right``, ``left``: the subject's)."""
    angle = eye_angle(landmarks)
    out = {}
    for eye, (outer, inner) in EYE_CORNERS.items():
        a, b = landmarks[outer, :2], landmarks[inner, :2]
        side = EYE_SCALE * float(np.linalg.norm(b - a))
        centre = (a + b) / 2
        out[eye] = Rect(float(centre[0]), float(centre[1]), side, side, angle, mirror=eye == "left")
    return out


def irises(rgb: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(iris ``[2, 5, 3]``, eye contours ``[2, 71, 3]``) in image pixels; eyes in the order right, left (the
    subject's); iris points: centre first."""
    model = load_model("iris_landmark")
    iris, contour = [], []
    for rect in eye_rois(landmarks).values():
        x = crop(rgb, rect, IRIS_SIZE, IRIS_SIZE) * (1.0 / 255.0)
        outs = {o.shape[-1]: o.reshape(-1, 3) for o in model(x[None])}
        iris.append(_to_image(outs[15], rect, IRIS_SIZE))
        contour.append(_to_image(outs[213], rect, IRIS_SIZE))
    return np.stack(iris), np.stack(contour)


def _to_image(points: np.ndarray, rect: Rect, size: int) -> np.ndarray:
    xy = rect.to_image(points[:, :2], size, size)
    return np.concatenate([xy, points[:, 2:3] * (rect.w / size)], -1)


def _mesh_outputs(outs: list[np.ndarray]) -> tuple[np.ndarray, float]:
    """(points [468, 3], presence logit) from the face mesh's outputs, in whichever order it lists them."""
    points = next(o for o in outs if o.size == 468 * 3).reshape(468, 3)
    logit = next(o for o in outs if o.size == 1).reshape(())
    return points, float(logit)
