"""The built-in CPU face tracker: from an ordinary video to a tracked dataset, one small stage per module.

Stage 1, video in (:mod:`.video`, :mod:`.crop`): MP4/MOV/WebM/MKV through PyAV, limits refused from the metadata
before decoding (:class:`~.video.VideoLimits`: 5 minutes, 4096 pixels on the long side, 9000 frames), rotation
metadata honoured, a variable frame rate resampled to a constant one (a constant one passed through), then frames
cut to the training resolution around the head (:func:`~.crop.crop_windows`) or whole (``none``).

Stage 2, detection and dense landmarks (:mod:`.detect`, :mod:`.mesh`, :mod:`.segment`, :mod:`.landmarks`):
MediaPipe's face detectors, face mesh (468 points), iris model (5 points per eye) and selfie segmentation, run with
LiteRT (:mod:`.runner`) from the files in ``models/`` (extracted from the mediapipe wheel by :mod:`.fetch_models`,
Apache-2.0, checked against their sha256), with our own pre- and post-processing; the largest face tracked from frame
to frame, re-detected when lost, short gaps interpolated and long ones reported.

Stage 3, fitting (:mod:`.correspond`, :mod:`.fit`): the open head fitted to the landmarks through a fixed, shipped
landmark-to-surface correspondence - focal length on keyframes, then per frame head pose and the 52 expressions
(jaw = jawOpen, gaze = eyeLook*, as ``data synth`` writes them), batched Gauss-Newton in torch; then the head
pose refined on the frames' own pixels (:mod:`.photometric`: the skin's grey levels held constant). Identity: the open
head has no shape basis, so its template is kept (the tracked-video format has no identity offsets yet). Stage 4
(:mod:`.track`, ``blendsplat track``): the dataset in the tracked-video format, head mattes as masks, the last 15%
held out, and a contact sheet of the fitted points.

Timings, 512x512 RGB, one CPU core (LiteRT and torch each on one thread), on the 2-core development machine while
other work ran (median of 60 runs; the model alone in brackets):

===============================  =========================
detection, short range           0.9-1.0 ms (0.64 ms)
detection, full range            2.2-2.7 ms (1.8 ms)
face mesh, 468 landmarks         1.4-1.6 ms (0.69 ms)
irises, both eyes                1.6-1.7 ms (2 x 0.58 ms)
segmentation (person)            2.8-3.2 ms (2.0 ms)
segmentation + head matte        3.5-5.6 ms
tracking, per frame              4-6 ms (mesh + irises; detection on the first frame and every 30th)
===============================  =========================

At 1920x1080 (a face of about 200 pixels) a tracked frame takes 6-7 ms, full-range detection 2.7-3.0 ms.
"""

from __future__ import annotations

from .crop import Window, crop_frame, crop_windows, whole_frame
from .detect import Detection, detect_faces
from .landmarks import FaceFrame, FaceTracker, LandmarkTrack, find_face, track_landmarks
from .mesh import POINTS, face_mesh, irises
from .segment import head_matte, person_probability
from .video import Frame, VideoInfo, VideoLimits, VideoReader, probe_video

__all__ = ["POINTS", "Detection", "FaceFrame", "FaceTracker", "Frame", "LandmarkTrack", "VideoInfo", "VideoLimits",
           "VideoReader", "Window", "crop_frame", "crop_windows", "detect_faces", "face_mesh", "find_face",
           "head_matte", "irises", "person_probability", "probe_video", "track_landmarks", "whole_frame"]
