"""``blendsplat bench track``: the CPU face tracker on an ordinary video with a known answer.

``data synth`` renders a seeded performance of the open head (known pose, expressions, camera), the frames are
encoded as an ordinary H.264 MP4 (yuv420p, as a phone writes), and :func:`~render_core.tracking.track.track_video`
tracks it back with ``crop="none"`` (the principal point at the image centre, as the truth has it). The report: the
tracker's stage split (``timing_ms``: decode, landmarks, fit, write), frames per second for landmarks + fit and for
the whole command, and the known answer (:func:`~render_core.tracking.known_answer.known_answer`) per seed and as
medians over the seeds.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def bench_track(seeds: tuple[int, ...] = (123,), frames: int = 150, size: int = 512,
                threads: int | None = None) -> dict:
    from ..data.portable import read_dataset
    from ..facemodel.open_head import open_head
    from ..tracking.known_answer import known_answer, synth_video
    from ..tracking.track import track_video

    model = open_head()
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-track-") as tmp:
        for seed in seeds:
            folder = Path(tmp) / str(seed)
            truth, video = synth_video(folder, frames, size, seed, model)
            t0 = time.perf_counter()
            report = track_video(video, folder / "tracked", size=size, crop="none", threads=threads)
            wall = time.perf_counter() - t0
            figures = known_answer(model, truth.tracking, read_dataset(folder / "tracked").tracking)
            t = report["timing_ms"]
            runs.append({"seed": seed, "wall_s": round(wall, 2), "timing_ms": t,
                         "frames_per_second": {
                             "landmarks_and_fit": round(frames / ((t["landmarks"] + t["fit"]) / 1e3), 1),
                             "whole": round(frames / wall, 1)},
                         "focal_px": report["focal_px"], "focal_truth_px": round(float(truth.tracking.K[0, 0, 0]), 2),
                         "known_answer": figures})

    def median(get) -> float:
        return round(float(np.median([get(r) for r in runs])), 3)

    return {"frames": frames, "size": size, "seeds": list(seeds), "threads": threads or torch.get_num_threads(),
            "runs": runs,
            "landmarks_and_fit_fps": median(lambda r: r["frames_per_second"]["landmarks_and_fit"]),
            "whole_fps": median(lambda r: r["frames_per_second"]["whole"]),
            "median_vertex_px": median(lambda r: r["known_answer"]["median_vertex_px"]),
            "median_head_rotation_deg": median(lambda r: r["known_answer"]["median_head_rotation_deg"]),
            "median_jaw_deg": median(lambda r: r["known_answer"]["median_jaw_deg"]),
            "mean_expression_mm": median(lambda r: r["known_answer"]["mean_expression_mm"])}
