"""Stage 4 and the whole tracker: a video in, a tracked dataset out (``blendsplat track VIDEO --out DIR``).

1. Decode (:mod:`.video`; ``max_seconds``: only the frames before that time are used) and find the face's landmarks
   in every frame (:mod:`.landmarks`): on the training crop itself for ``crop="none"`` (the whole frame fitted into
   ``size`` x ``size``), on the full frame for ``auto`` (one fixed head window for the video, :mod:`.crop`), the
   landmarks then mapped into the crop.
2. Fit (:mod:`.fit`) the kept frames (found or interpolated; dropped frames are left out of the dataset, with their
   reasons in the report), the principal point at the image of the frame's centre.
3. Decode again and write (:func:`~render_core.data.portable.write_dataset`, PNG): the crops, the head mattes
   (:mod:`.segment`, selfie segmentation limited to the head) as masks, and ``tracking.npz`` exactly as ``data
   synth`` writes it for the open head (joints at rest, eyelids zero, no identity shape; jaw = ``jawOpen``, gaze =
   ``eyeLook*``), the last 15% of the frames held out as the test set. Then ``contact_sheet.png`` in the folder (not
   part of the format, which ignores other files): a few frames with the detected points (red) and the fitted
   model's projected points (green).
"""

from __future__ import annotations

import itertools
import os
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..data.generate import torch_threads
from ..errors import TrackingError
from .crop import crop_frame, crop_windows, whole_frame
from .landmarks import track_landmarks
from .video import VideoLimits, VideoReader

CROPS = ("auto", "none")
PHOTOMETRIC = ("on", "poses", "off")  # what the refinement on the pixels refines: poses and expressions, poses, nothing
SHEET_FRAMES = 6
MIN_FRAMES = 10  # fewer frames with a face: "too short" to train an avatar on


def _frames(reader: VideoReader, max_seconds: float | None) -> Iterator:
    for frame in reader:
        if max_seconds is not None and frame.time >= max_seconds:
            return
        yield frame


def _dots(img: np.ndarray, points: np.ndarray, colour: tuple[int, int, int], r: int = 1) -> None:
    h, w = img.shape[:2]
    for x, y in np.round(points[:, :2] - 0.5).astype(np.int64):
        img[max(0, y - r):min(h, y + r + 1), max(0, x - r):min(w, x + r + 1)] = colour


def _sheet(tiles: list[np.ndarray], path: Path) -> Path:
    from ..media.files import write_image

    cols = min(3, len(tiles))
    rows = -(-len(tiles) // cols)
    h, w = tiles[0].shape[:2]
    sheet = np.zeros((rows * h, cols * w, 3), np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    write_image(path, sheet)
    return path


def track_video(video: str | os.PathLike, out: str | os.PathLike, *, fps: float | None = None, size: int = 512,
                crop: str = "auto", max_seconds: float | None = None, threads: int | None = None,
                progress: Callable[[str], None] | None = None, limits: VideoLimits | None = None,
                min_frames: int = MIN_FRAMES, focal: float | None = None, photometric: str = "on") -> dict:
    """Track ``video`` into the dataset folder ``out`` (module docstring); returns the report: frames_kept,
    frames_dropped (count and runs with reasons), reprojection_px (median over the kept frames), focal, faces (the
    most seen at once, frames with several: the largest was tracked), timing_ms.

    ``progress`` gets ``"<step>: <detail>"`` lines (steps ``landmarks`` - every 5% of the frames -, ``fit``,
    ``write``; no paths in them) and may raise to stop the tracking (a cancelled job). ``limits``: the video's
    (default :class:`~.video.VideoLimits`). ``focal``: the focal length in pixels of the output frames when it is
    known (a phone records it), instead of searching it from the landmarks (:func:`~.fit.search_focal`).
    ``photometric``: after the landmark fit, refine the head poses and then the expressions on the frames' pixels
    (``"on"``, :mod:`.photometric`), the poses only (``"poses"``) or neither (``"off"``).
    ``threads``: CPU threads (default None: torch's, the machine's cores, as the CLI and the job workers run; 1:
    one core: the irises and the mattes made in turn on the calling thread). Fewer than ``min_frames`` frames with
    a face is a ``TrackingError`` on ``frames`` (too short)."""
    from ..data.generate import held_out_count
    from ..data.portable import Tracking, write_dataset
    from ..facemodel.open_head import open_head
    from .fit import fit_frames
    from .photometric import EXPRESSION_PASSES, refine_on_pixels
    from .segment import head_matte, mesh_silhouette, person_probability, sharpen_edge

    if crop not in CROPS:
        raise TrackingError(f"unknown crop {crop!r}; one of {', '.join(CROPS)}", field="crop")
    if photometric not in PHOTOMETRIC:
        raise TrackingError(f"unknown refinement {photometric!r}; one of {', '.join(PHOTOMETRIC)}", field="photometric")
    if focal is not None and not (0 < focal < 100 * size):  # refused before anything is decoded
        raise TrackingError(f"must be a positive number of pixels below {100 * size}, got {focal}", field="focal")
    say = progress or (lambda s: None)
    out = Path(out)
    timing = {"decode": 0.0, "landmarks": 0.0, "fit": 0.0, "write": 0.0}
    reader = VideoReader(video, fps=fps, limits=limits or VideoLimits())
    W, H = reader.info.width, reader.info.height
    window = whole_frame(W, H, size, size)
    every = max(30, len(reader) // 20)

    def inputs() -> Iterator[np.ndarray]:
        it = _frames(reader, max_seconds)
        for i in itertools.count():
            if i % every == 0:
                say(f"landmarks: frame {i} of {len(reader)}")
            t0 = time.perf_counter()
            frame = next(it, None)
            rgb = None if frame is None else (crop_frame(frame.rgb, window) if crop == "none" else frame.rgb)
            timing["decode"] += time.perf_counter() - t0
            if rgb is None:
                return
            yield rgb

    t0 = time.perf_counter()
    track = track_landmarks(inputs(), threads=threads)
    timing["landmarks"] = time.perf_counter() - t0 - timing["decode"]
    landmarks, iris = track.landmarks, track.iris
    if crop == "auto":
        window = crop_windows(track.boxes, W, H, size, size, "fixed")[0]
        landmarks, iris = window.to_crop(landmarks), window.to_crop(iris)
    kept = track.kept
    if len(kept) < min_frames:
        raise TrackingError(f"the video is too short: a face in {len(kept)} frames, at least {min_frames} are needed",
                            field="frames")
    say(f"fit: {len(kept)} frames")
    t0 = time.perf_counter()
    model = open_head()
    principal = tuple(window.to_crop(np.array([[W / 2, H / 2]]))[0])
    fit = fit_frames(model, landmarks[kept], iris[kept], size, size, principal=principal, focal=focal,
                     threads=threads)
    n = len(kept)
    where = {int(f): k for k, f in enumerate(kept)}
    if photometric != "off":
        say(f"fit: refining {n} frames on the pixels")
        decode_before = timing["decode"]
        fit = refine_on_pixels(model, fit, landmarks[kept], iris[kept],
                               lambda: _grey_chunks(reader, max_seconds, where, window, timing), threads=threads,
                               expression_passes=EXPRESSION_PASSES if photometric == "on" else 0,
                               focal=focal is None)
        t0 += timing["decode"] - decode_before  # the second decode counts as decoding
    timing["fit"] = time.perf_counter() - t0

    n_test = held_out_count(n) if n >= 2 else 0
    tracking = Tracking(
        face_model=model.name, expression_names=list(model.expression_names), joint_names=list(model.joint_names),
        expression=fit.expression.astype(np.float32), joint_rotations=np.zeros((n, model.num_joints, 3), np.float32),
        eyelids=np.zeros((n, 2), np.float32), K=np.broadcast_to(fit.K, (n, 3, 3)).astype(np.float32),
        R=fit.R.astype(np.float32), t=fit.t.astype(np.float32), shape=np.zeros(0, np.float32),
        train=np.arange(n - n_test), test=np.arange(n - n_test, n), width=size, height=size,
        fps=float(reader.fps))
    sheet_at = set(np.unique(np.round(np.linspace(0, n - 1, min(SHEET_FRAMES, n))).astype(int)).tolist())
    tiles: list[np.ndarray] = []
    projected = _projected(model, fit)
    faces = model.faces.numpy()
    template, basis = model.template.double().numpy(), model.expression_basis.double().numpy()

    def posed(k: int) -> np.ndarray:  # frame k's fitted head in camera coordinates (joints at rest)
        X = template + np.einsum("k,kvc->vc", fit.expression[k], basis)
        return X @ fit.R[k].T + fit.t[k]

    say(f"write: {n} frames")
    t_write = time.perf_counter()
    decode_before = timing["decode"]

    def kept_frames() -> Iterator[tuple[int, np.ndarray]]:
        for i, frame in enumerate(_frames(reader, max_seconds)):
            if i in where:
                yield where[i], crop_frame(frame.rgb, window)

    def mask_of(k: int, rgb: np.ndarray) -> np.ndarray:
        head = mesh_silhouette(posed(k), faces, fit.K, size, size)
        prob = person_probability(rgb)
        matte = sharpen_edge(head_matte(prob, landmarks[kept[k]], silhouette=head, rgb=rgb))
        return np.round(255 * matte).astype(np.uint8)

    workers = threads or len(os.sched_getaffinity(0))
    masks: deque[np.ndarray] = deque()

    def frames_out() -> Iterator[np.ndarray]:
        for k, rgb, mask in _with_masks(kept_frames(), mask_of, workers):
            masks.append(mask)
            if k in sheet_at:
                tile = rgb.copy()
                _dots(tile, landmarks[kept[k], track_points(fit)], (230, 40, 40))
                _dots(tile, projected[k], (40, 230, 40))
                tiles.append(tile)
            yield rgb

    def masks_out() -> Iterator[np.ndarray]:
        while masks:
            yield masks.popleft()

    with torch_threads(1 if workers > 1 else threads):
        write_dataset(out, frames_out(), masks_out(), tracking, image_format="png")
    if tiles:
        _sheet(tiles, out / "contact_sheet.png")
    timing["write"] = time.perf_counter() - t_write - (timing["decode"] - decode_before)
    dropped, seen = len(track.status) - n, track.report()
    return {"out": str(out), "frames_kept": n, "frames_dropped": {"count": dropped, "runs": seen["dropped_runs"]},
        "interpolated": track.status.count("interpolated"),
        "reprojection_px": round(float(np.median(fit.reprojection_px)), 3), "focal_px": round(float(fit.K[0, 0]), 2),
        "size": size, "crop": crop, "fps": float(reader.fps), "train": n - n_test, "test": n_test,
        **{k: seen[k] for k in ("max_faces", "frames_with_several_faces")},
        "timing_ms": {k: round(1000 * v, 1) for k, v in timing.items()},
        "frames_per_second": {"landmarks_and_fit": round(len(track.status) / max(timing["landmarks"]
                                                                                 + timing["fit"], 1e-9), 1)}}


def _with_masks(frames: Iterator[tuple[int, np.ndarray]], mask_of: Callable[[int, np.ndarray], np.ndarray],
                workers: int, ahead: int = 8) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """``(k, rgb)`` -> ``(k, rgb, mask_of(k, rgb))`` in order; with several ``workers``, the masks are made on that
    many threads at most ``ahead`` frames ahead while the caller writes (the selfie model, numpy and the PNG encoder
    release the GIL: the write stage of 150 frames at 512x512 in 0.45x the time on 2 cores)."""
    if workers <= 1:
        for k, rgb in frames:
            yield k, rgb, mask_of(k, rgb)
        return
    with ThreadPoolExecutor(workers, thread_name_prefix="matte") as pool:
        queue: deque = deque()
        for k, rgb in frames:
            queue.append((k, rgb, pool.submit(mask_of, k, rgb)))
            if len(queue) > ahead:
                k, rgb, job = queue.popleft()
                yield k, rgb, job.result()
        while queue:
            k, rgb, job = queue.popleft()
            yield k, rgb, job.result()


def _grey_chunks(reader: VideoReader, max_seconds: float | None, where: dict[int, int], window,
                 timing: dict[str, float]) -> Iterator[tuple[list[int], np.ndarray]]:
    """The kept frames decoded again, cut to the training crop and turned grey, in chunks of
    :data:`~.photometric.CHUNK` frames: (their indices among the kept frames, ``[n, H, W]`` float32)."""
    from .photometric import CHUNK, grey

    idx: list[int] = []
    images: list[np.ndarray] = []
    t0 = time.perf_counter()
    for i, frame in enumerate(_frames(reader, max_seconds)):
        k = where.get(i)
        if k is not None:
            idx.append(k)
            images.append(grey(crop_frame(frame.rgb, window)))
        if len(idx) == CHUNK:
            timing["decode"] += time.perf_counter() - t0
            yield idx, np.stack(images)
            idx, images, t0 = [], [], time.perf_counter()
    timing["decode"] += time.perf_counter() - t0
    if idx:
        yield idx, np.stack(images)


def track_points(fit) -> np.ndarray:
    """The MediaPipe indices of the fitted points that are face-mesh landmarks (irises excluded)."""
    from .correspond import load_correspondence

    idx = load_correspondence().landmarks
    return idx[idx < 468]


def _projected(model, fit) -> np.ndarray:
    """The fitted model's face-mesh points (irises excluded) projected in every kept frame ``[N, L', 2]``."""
    import torch

    from .fit import R0, Problem, matrix_to_axis_angle

    problem = Problem(model)
    rotation = matrix_to_axis_angle(R0.T @ torch.from_numpy(fit.R).double())
    X = problem.anchors(rotation) + torch.einsum("nk,klc->nlc", torch.from_numpy(fit.expression).double(), problem.B)
    Xc = X.numpy() @ np.swapaxes(fit.R, 1, 2) + fit.t[:, None]
    uv = Xc @ fit.K.T
    uv = uv[..., :2] / uv[..., 2:3]
    return uv[:, problem.corr.landmarks < 468]
