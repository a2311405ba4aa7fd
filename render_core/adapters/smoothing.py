"""The One Euro filter (Casiez, Roussel and Vogel, CHI 2012) for noisy tracker coefficients, per component.

For a sample x at time t (dt after the previous one):

    alpha(f) = 1 / (1 + 1 / (2 pi f dt))
    dx  = alpha(d_cutoff) (x - x_prev) / dt + (1 - alpha(d_cutoff)) dx_prev      (smoothed speed)
    f_c = min_cutoff + beta |dx|
    x^  = alpha(f_c) x + (1 - alpha(f_c)) x^_prev

Slow motion is smoothed strongly (cutoff ``min_cutoff`` Hz: jitter goes), fast motion lightly (cutoff grows with
the speed: little lag). The first sample passes unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .manifest import AdapterError


@dataclass
class OneEuroFilter:
    min_cutoff: float = 1.0  # Hz
    beta: float = 0.0
    d_cutoff: float = 1.0  # Hz
    default_rate: float = 30.0  # Hz, when two samples carry no usable time difference

    def __post_init__(self) -> None:
        for name in ("min_cutoff", "beta", "d_cutoff", "default_rate"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0 or (v == 0 and name != "beta"):
                raise AdapterError(f"must be a finite number{' >= 0' if name == 'beta' else ' > 0'}, got {v}",
                                   field=f"smoothing.{name}")
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None
        self._t: float | None = None

    @staticmethod
    def _alpha(cutoff: np.ndarray | float, dt: float) -> np.ndarray | float:
        return 1.0 / (1.0 + 1.0 / (2 * math.pi * cutoff * dt))

    def __call__(self, x: np.ndarray, t: float | None = None) -> np.ndarray:
        """Filter one sample (any shape; the same shape every call), taken at ``t`` seconds."""
        x = np.asarray(x, np.float64)
        if self._x is None or self._x.shape != x.shape:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), t
            return x.copy()
        dt = (t - self._t) if (t is not None and self._t is not None) else 0.0
        if not dt > 0:
            dt = 1.0 / self.default_rate
        self._t = t
        dx = (x - self._x) / dt
        a_d = self._alpha(self.d_cutoff, dt)
        self._dx = a_d * dx + (1 - a_d) * self._dx
        a = self._alpha(self.min_cutoff + self.beta * np.abs(self._dx), dt)
        self._x = a * x + (1 - a) * self._x
        return self._x.copy()

    def reset(self) -> None:
        self._x = self._dx = self._t = None
