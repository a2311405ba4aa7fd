"""The poses `blendsplat bench stream` sends: ``smooth`` (as a person moves) or ``random`` (independent frames).

- ``smooth`` (the default): every expression coefficient and every axis of every joint (but the root) is a sinusoid
  of its own frequency (0.1 to 1.9 Hz, all under 2 Hz), amplitude and phase, drawn per stream from its seed, and
  sampled at the frame's time (index / fps). Consecutive frames differ little, as a tracked face's do: the case
  that temporal coherence (a previous frame's depth order, tile lists) is for. Coefficients go from 0 to their
  amplitude (up to 0.6: on average as far from rest as the random drive's), joint angles swing up to 0.15 rad
  either way (the random drive's 0.08 rad standard deviation is an amplitude of 0.11).
- ``random``: each frame's coefficients and rotations drawn afresh (a few active expressions, like speech, and
  N(0, 0.08) rad per joint axis), so no frame resembles the one before: the worst case for temporal reuse.

The pose of a frame depends only on the stream's seed and the frame's index (and fps, for smooth), so a benchmark's
poses can be rebuilt, and a frame's pose is the same whichever frames were dropped.
"""

from __future__ import annotations

import time

import numpy as np

from blendsplat.v1 import render_pb2 as pb

DRIVES = ("smooth", "random")
MAX_HZ = 1.9  # every sinusoid of the smooth drive is below 2 Hz
MIN_HZ = 0.1
MAX_COEFFICIENT = 0.6
MAX_ANGLE = 0.15  # radians


class Drive:
    """The poses of one stream: :meth:`pose` builds frame ``index``'s FrameParams (``kind``: smooth or random)."""

    def __init__(self, kind: str, seed: int, names: list[str], joints: list[str], fps: float):
        if kind not in DRIVES:
            raise ValueError(f"drive must be one of {', '.join(DRIVES)}, got {kind!r}")
        self.kind, self.seed, self.fps = kind, seed, fps
        self.k = len(names)
        self.joints = [name for name in joints if name != "root"]
        self._rng = np.random.default_rng(seed)  # the random drive's, drawn frame after frame
        rng = np.random.default_rng([seed, 1])  # the smooth drive's sinusoids: fixed for the stream
        n = self.k + 3 * len(self.joints)
        self.hz = rng.uniform(MIN_HZ, MAX_HZ, n)
        self.phase = rng.uniform(0.0, 2 * np.pi, n)
        self.amplitude = np.concatenate([rng.uniform(0.0, MAX_COEFFICIENT, self.k),
                                         rng.uniform(0.3 * MAX_ANGLE, MAX_ANGLE, 3 * len(self.joints))])

    def values(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``'s coefficients [K] and axis-angle rotations [joints, 3] (smooth: a function of the index
        alone; random: the next draw)."""
        if self.kind == "random":
            rng = self._rng
            coeffs = rng.uniform(0.0, 1.0, self.k) * (rng.uniform(0, 1, self.k) < 0.3)
            return coeffs, rng.normal(0, 0.08, (len(self.joints), 3))
        wave = np.cos(2 * np.pi * self.hz * (index / self.fps) + self.phase)
        coeffs = self.amplitude[:self.k] * 0.5 * (1.0 - wave[:self.k])  # 0 .. amplitude
        angles = self.amplitude[self.k:] * wave[self.k:]  # -amplitude .. amplitude
        return coeffs, angles.reshape(len(self.joints), 3)

    def pose(self, index: int) -> pb.FrameParams:
        coeffs, angles = self.values(index)
        rotations = {name: pb.Rotation(values=a.tolist()) for name, a in zip(self.joints, angles, strict=True)}
        return pb.FrameParams(index=index, client_time_us=time.time_ns() // 1000, coefficients=coeffs.tolist(),
                              joints=rotations)
