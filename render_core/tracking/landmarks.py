"""Stage 2: a face's dense landmarks through a video - detect it, track it from frame to frame, fill short gaps.

:class:`FaceTracker` follows one face: on the first frame (and whenever the face is lost) it runs the detector
(:mod:`.detect`; the short-range model, then the full-range one when that finds nothing) and takes the LARGEST face;
on later frames the face mesh's crop comes from the previous frame's landmarks (:mod:`.mesh`), and when the mesh
says the crop holds no face (presence <= 0.5) the detector runs again on that frame. Every ``detect_every`` frames
the detector also runs while tracking, to count the faces in view (the tracked face stays the one followed: an
avatar is of one person). Each found face also gets its irises (5 points per eye).

:func:`track_landmarks` runs the tracker over frames and returns a :class:`LandmarkTrack`: a frame without a face
is interpolated (linearly, from the frames either side) when its gap is at most ``max_gap`` frames, else dropped with
its reason (a long gap; before the face was first found; after it was last seen). No face in any frame is a
:class:`~render_core.errors.TrackingError` on ``face``. The head matte (:mod:`.segment`) is not part of the loop:
it is computed on the training crops (stage 1's :func:`~.video.crop_frame`), with the landmarks mapped into them.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ..data.generate import torch_threads
from ..errors import TrackingError
from .detect import Detection, detect_faces
from .mesh import PRESENCE, face_mesh, irises, roi_from_detection, roi_from_landmarks

STATUSES = ("detected", "tracked", "interpolated", "dropped")
IRIS_QUEUE = 4  # frames whose irises may wait (each holds its picture)


@dataclass
class FaceFrame:
    """One frame's face: ``landmarks [468, 3]`` and ``iris [2, 5, 3]`` (subject's right, left eye) in image pixels,
    the face mesh's ``presence``, ``source`` (``detected`` or ``tracked``), and ``faces``: how many faces the
    detector saw in this frame (-1: it did not run)."""

    landmarks: np.ndarray
    iris: np.ndarray
    presence: float
    source: str
    faces: int = -1

    @property
    def box(self) -> np.ndarray:
        """The landmarks' bounding box (x0, y0, x1, y1)."""
        return landmark_box(self.landmarks)


def landmark_box(landmarks: np.ndarray) -> np.ndarray:
    xy = landmarks[..., :2]
    return np.concatenate([xy.min(-2), xy.max(-2)], -1)


class FaceTracker:
    """Frame-to-frame tracking of one face (module docstring). ``step(rgb)`` -> :class:`FaceFrame` or None."""

    def __init__(self, detector: str = "auto", detect_every: int = 30, iris: bool = True,
                 presence: float = PRESENCE):
        if detector not in ("auto", "short", "full"):
            raise TrackingError(f"unknown detector {detector!r}; auto, short or full", field="detector")
        self.detector, self.detect_every, self.iris, self.presence = detector, max(1, detect_every), iris, presence
        self._previous: np.ndarray | None = None  # the last frame's landmarks
        self._since_detection = 0
        self.detections = 0  # detector runs

    def reset(self) -> None:
        self._previous = None

    def _detect(self, rgb: np.ndarray) -> list[Detection]:
        self.detections += 1
        self._since_detection = 0
        faces = detect_faces(rgb, "short" if self.detector == "auto" else self.detector)
        if not faces and self.detector == "auto":
            faces = detect_faces(rgb, "full")
        return faces

    def step(self, rgb: np.ndarray) -> FaceFrame | None:
        """The face in ``rgb [H, W, 3]`` uint8, or None when there is none (the next frame detects again)."""
        frame = self.find(rgb)
        if frame is not None and self.iris:
            frame.iris = irises(np.asarray(rgb)[..., :3], frame.landmarks)[0]
        return frame

    def find(self, rgb: np.ndarray) -> FaceFrame | None:
        """As :meth:`step` without the irises (NaN): the next frame's crop needs only this frame's face mesh, so a
        caller may find the irises meanwhile (:func:`track_landmarks`)."""
        rgb = np.asarray(rgb)[..., :3]
        found: tuple[np.ndarray, float, str] | None = None  # landmarks, presence, source
        faces = -1
        if self._previous is not None:
            self._since_detection += 1
            if self._since_detection >= self.detect_every:
                faces = len(self._detect(rgb))
            landmarks, presence = face_mesh(rgb, roi_from_landmarks(self._previous))
            if presence > self.presence:
                found = landmarks, presence, "tracked"
        if found is None:
            detections = self._detect(rgb)
            faces = len(detections)
            if detections:  # the largest
                landmarks, presence = face_mesh(rgb, roi_from_detection(detections[0]))
                if presence > self.presence:
                    found = landmarks, presence, "detected"
        if found is None:
            self._previous = None
            return None
        landmarks, presence, source = found
        self._previous = landmarks
        return FaceFrame(landmarks, np.full((2, 5, 3), np.nan), presence, source, faces)


@dataclass
class LandmarkTrack:
    """Landmarks of N frames: ``landmarks [N, 468, 3]``, ``iris [N, 2, 5, 3]``, ``boxes [N, 4]`` (the landmarks'
    box), ``presence [N]`` (NaN where not found), ``status`` per frame (STATUSES), ``faces [N]`` (faces the detector
    saw, -1 where it did not run) and ``dropped``: the dropped runs (start, end inclusive, reason)."""

    landmarks: np.ndarray
    iris: np.ndarray
    boxes: np.ndarray
    presence: np.ndarray
    status: list[str]
    faces: np.ndarray
    dropped: list[tuple[int, int, str]] = field(default_factory=list)

    @property
    def kept(self) -> np.ndarray:
        """Indices of the frames kept (found or interpolated)."""
        return np.array([i for i, s in enumerate(self.status) if s != "dropped"], dtype=np.int64)

    def report(self) -> dict:
        """Counts per status, the dropped runs with reasons, and the faces seen (most at once; frames with several)."""
        counts = {s: self.status.count(s) for s in STATUSES}
        seen = self.faces[self.faces >= 0]
        return {"frames": len(self.status), "kept": len(self.status) - counts["dropped"], **counts,
                "dropped_runs": [{"start": a, "end": b, "frames": b - a + 1, "reason": r} for a, b, r in self.dropped],
                "max_faces": int(seen.max()) if seen.size else 0, "frames_with_several_faces": int((seen > 1).sum())}


def track_landmarks(frames: Iterable[np.ndarray], max_gap: int = 5, tracker: FaceTracker | None = None, *,
                    threads: int | None = 1, **tracker_options) -> LandmarkTrack:
    """Track the face through ``frames`` (RGB uint8 ``[H, W, 3]`` each) and fill or drop its gaps (module
    docstring). ``tracker_options`` go to :class:`FaceTracker` when no ``tracker`` is given; ``threads``: torch's
    threads for the crops meanwhile (None: unchanged); with more than one (or None), a second thread finds each
    frame's irises while the tracker goes on to the next frame, at most :data:`IRIS_QUEUE` frames behind, torch on
    one thread in each (the models release the GIL: 150 frames at 512x512 in 0.65x the time on 2 cores; torch's own
    threads beside them took that gain away)."""
    tracker = tracker or FaceTracker(**tracker_options)
    pipelined = threads != 1 and tracker.iris
    with torch_threads(1 if pipelined else threads):
        found: list[FaceFrame | None] = _pipelined(tracker, frames) if pipelined else [tracker.step(f) for f in frames]
    n = len(found)
    if not any(f is not None for f in found):
        raise TrackingError(f"no face found in any of the {n} frames", field="face")
    landmarks = np.full((n, 468, 3), np.nan, dtype=np.float32)
    iris = np.full((n, 2, 5, 3), np.nan, dtype=np.float32)
    presence = np.full(n, np.nan, dtype=np.float32)
    faces = np.full(n, -1, dtype=np.int64)
    status = ["dropped"] * n
    for i, f in enumerate(found):
        if f is not None:
            landmarks[i], iris[i], presence[i], status[i], faces[i] = f.landmarks, f.iris, f.presence, f.source, f.faces
    dropped = _fill_gaps(status, [landmarks, iris], max_gap)
    return LandmarkTrack(landmarks, iris, landmark_box(landmarks), presence, status, faces, dropped)


def _pipelined(tracker: FaceTracker, frames: Iterable[np.ndarray]) -> list[FaceFrame | None]:
    """:meth:`FaceTracker.step` over ``frames``, the irises found on a second thread."""
    from concurrent.futures import Future, ThreadPoolExecutor

    def with_irises(frame: FaceFrame, rgb: np.ndarray) -> None:
        frame.iris = irises(rgb, frame.landmarks)[0]

    found: list[FaceFrame | None] = []
    pending: list[Future] = []
    with ThreadPoolExecutor(1, thread_name_prefix="irises") as pool:
        for rgb in frames:
            rgb = np.asarray(rgb)[..., :3]
            frame = tracker.find(rgb)
            found.append(frame)
            if frame is not None:
                pending.append(pool.submit(with_irises, frame, rgb))
            while len(pending) > IRIS_QUEUE or (pending and pending[0].done()):
                pending.pop(0).result()
        for future in pending:
            future.result()
    return found


def _fill_gaps(status: list[str], arrays: list[np.ndarray], max_gap: int) -> list[tuple[int, int, str]]:
    """Interpolate the runs of ``dropped`` frames of at most ``max_gap`` between two found frames (in ``arrays``
    along their first axis; ``status`` updated); returns the runs left dropped with their reasons."""
    n = len(status)
    out = []
    i = 0
    while i < n:
        if status[i] != "dropped":
            i += 1
            continue
        j = i
        while j + 1 < n and status[j + 1] == "dropped":
            j += 1
        if i == 0:
            out.append((i, j, "before the face was first found"))
        elif j == n - 1:
            out.append((i, j, "after the face was last seen"))
        elif j - i + 1 > max_gap:
            out.append((i, j, f"face lost for {j - i + 1} frames (more than {max_gap} to interpolate)"))
        else:
            a, b = i - 1, j + 1
            for k in range(i, j + 1):
                w = (k - a) / (b - a)
                for arr in arrays:
                    arr[k] = (1 - w) * arr[a] + w * arr[b]
                status[k] = "interpolated"
        i = j + 1
    return out


def find_face(rgb: np.ndarray, detector: str = "auto", threads: int | None = 1) -> FaceFrame:
    """The largest face of one image (no tracking; ``faces``: how many the detector saw); none: TrackingError on
    ``face``."""
    with torch_threads(threads):
        frame = FaceTracker(detector=detector).step(rgb)
    if frame is None:
        raise TrackingError("no face found in the image", field="face")
    return frame
