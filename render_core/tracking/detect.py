"""Face detection: MediaPipe's BlazeFace detectors (short range 128x128, full range 192x192), with our own decoding.

The model sees the whole frame letterboxed into its square input (aspect kept, zero padding), RGB in [-1, 1]. Its
outputs are 16 regressors and a score logit per SSD anchor. The anchors sit at the centres of the feature-map cells
(``(i + 0.5) / cells``) with a fixed unit size: short range strides 8 (16x16 cells, 2 anchors each) and 16 (8x8
cells, 6 anchors each; its three stride-16 layers share one grid) = 896 anchors; full range stride 4 (48x48 cells,
1 anchor each) = 2304. Regressors, in input pixels relative to the anchor centre: box centre x, y, width, height,
then six keypoints (x, y): the subject's right eye, left eye, nose tip, mouth centre, right and left ear tragion
(the subject's right eye is on the image's left). The score is sigmoid(clip(logit, +-100)), kept above 0.5 (short
range) or 0.6 (full range); overlapping boxes (IoU > 0.3) are merged by the score-weighted mean of their boxes and
keypoints (weighted non-maximum suppression), the merged detection keeping the best score.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import letterbox
from .runner import load_model

# name -> (model, input size, [(stride, anchors per cell)], score threshold)
DETECTORS = {
    "short": ("face_detection_short_range", 128, [(8, 2), (16, 6)], 0.5),
    "full": ("face_detection_full_range_sparse", 192, [(4, 1)], 0.6),
}
NMS_IOU = 0.3
KEYPOINTS = ("right_eye", "left_eye", "nose_tip", "mouth_centre", "right_ear", "left_ear")


@dataclass(frozen=True)
class Detection:
    """A detected face in image pixels: ``box`` (x0, y0, x1, y1), ``keypoints [6, 2]`` (KEYPOINTS), ``score``."""

    box: np.ndarray
    keypoints: np.ndarray
    score: float

    @property
    def area(self) -> float:
        return float(max(self.box[2] - self.box[0], 0.0) * max(self.box[3] - self.box[1], 0.0))


def anchors(size: int, layers: list[tuple[int, int]]) -> np.ndarray:
    """``[A, 2]`` anchor centres (normalised x, y) for an input of ``size`` pixels, row-major per grid."""
    out = []
    for stride, per_cell in layers:
        cells = size // stride
        g = (np.arange(cells) + 0.5) / cells
        x, y = np.meshgrid(g, g)
        out.append(np.repeat(np.stack([x.ravel(), y.ravel()], -1), per_cell, axis=0))
    return np.concatenate(out)


_ANCHORS = {name: anchors(size, layers) for name, (_, size, layers, _) in DETECTORS.items()}


def decode(regressors: np.ndarray, logits: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw outputs ``[A, 16]``, ``[A]`` -> (boxes ``[A, 4]`` x0 y0 x1 y1, keypoints ``[A, 6, 2]``, scores ``[A]``),
    normalised to the model's input square."""
    _, size, _, _ = DETECTORS[kind]
    a = _ANCHORS[kind]
    r = regressors.astype(np.float64) / size
    cx, cy = r[:, 0] + a[:, 0], r[:, 1] + a[:, 1]
    w, h = r[:, 2], r[:, 3]
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], -1)
    keypoints = r[:, 4:16].reshape(-1, 6, 2) + a[:, None, :]
    scores = 1.0 / (1.0 + np.exp(-np.clip(logits.astype(np.float64), -100.0, 100.0)))
    return boxes, keypoints, scores


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0, y0 = np.maximum(box[0], boxes[:, 0]), np.maximum(box[1], boxes[:, 1])
    x1, y1 = np.minimum(box[2], boxes[:, 2]), np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray,
                 threshold: float = NMS_IOU) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Merge overlapping candidates: best first, each cluster (IoU > threshold with the best remaining) becomes its
    score-weighted mean box and keypoints with the best score."""
    order = np.argsort(-scores, kind="stable")
    out = []
    while order.size:
        overlap = iou(boxes[order[0]], boxes[order]) > threshold
        cluster, order = order[overlap], order[~overlap]
        w = scores[cluster][:, None]
        box = (boxes[cluster] * w).sum(0) / w.sum()
        kps = (keypoints[cluster] * w[:, :, None]).sum(0) / w.sum()
        out.append((box, kps, float(scores[cluster[0]])))
    return out


def detect_faces(rgb: np.ndarray, kind: str = "short", threshold: float | None = None) -> list[Detection]:
    """Faces in an RGB uint8 frame ``[H, W, 3]``, largest first, in image pixels."""
    name, size, _, default_threshold = DETECTORS[kind]
    picture, square = letterbox(rgb, size)  # the frame centred in a square, zero around it
    x = picture * (2.0 / 255.0) - 1.0  # the padding (zero) is -1: black
    regressors, logits = _outputs(load_model(name)(x[None]))
    boxes, keypoints, scores = decode(regressors, logits, kind)
    keep = scores >= (default_threshold if threshold is None else threshold)
    faces = []
    for box, kps, score in weighted_nms(boxes[keep], keypoints[keep], scores[keep]):
        corners = square.to_image(box.reshape(2, 2), 1.0, 1.0).reshape(4)
        faces.append(Detection(corners, square.to_image(kps, 1.0, 1.0), score))
    return sorted(faces, key=lambda d: -d.area)


def _outputs(outs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(regressors [A, 16], logits [A]) from the model's two outputs, whichever order it lists them in."""
    a, b = (o.reshape(o.shape[-2], o.shape[-1]) for o in outs)
    regressors, logits = (a, b) if a.shape[1] == 16 else (b, a)
    return regressors, logits[:, 0]
