"""Metrical-tracker / INSTA subject folders (local, trusted data only) and their conversion to the portable format.

Layout read (docs/method.md sections 7 and 11)::

    checkpoint/00000.frame ...   torch-saved dict per frame:
        flame:   exp [1, 100], shape [1, 300], jaw [1, 6] (6D), eyes [1, 12] (6D eye_l then eye_r), eyelids [1, 2]
        opencv:  R [1, 3, 3], t [1, 3], K [1, 3, 3]   (world-to-camera, OpenCV axes, K in pixels at img_size)
        img_size [2]
    images/00000.png ...         RGBA, 8-bit; alpha is the foreground (head) mask

A ``.frame`` file is a pickle. It is loaded with ``torch.load(weights_only=True)``, which only rebuilds tensors,
numpy arrays and plain containers and never runs code; a file that needs anything else (a custom class, ...) is
refused with a DatasetError unless ``trusted=True`` is passed, which falls back to full unpickling - that can run
arbitrary code, so pass it only for folders you produced yourself. Uploads use the portable format instead.
"""

from __future__ import annotations

import os
import pickle
from collections import deque
from pathlib import Path

import numpy as np
import torch

from ..errors import DatasetError
from ..rotation import matrix_to_quat, rot6d_to_matrix
from .portable import Tracking, check_tracking, read_image, write_dataset

try:  # numpy >= 2
    from numpy._core import multiarray as _multiarray
except ImportError:  # pragma: no cover - numpy 1.x
    from numpy.core import multiarray as _multiarray

FACE_MODEL = "flame"
JOINT_NAMES = ["root", "neck", "jaw", "eye_l", "eye_r"]
FALLBACK_TEST_FRACTION = 0.15

# What a numpy array in a pickle refers to, under numpy 2 and numpy 1 names: rebuilding an array is data only.
_NUMPY_SAFE_GLOBALS = [
    _multiarray._reconstruct, (_multiarray._reconstruct, "numpy.core.multiarray._reconstruct"),
    _multiarray.scalar, (_multiarray.scalar, "numpy.core.multiarray.scalar"),
    np.ndarray, np.dtype,
    *(t for t in vars(np.dtypes).values() if isinstance(t, type) and issubclass(t, np.dtype)),  # Float32DType, ...
]


def load_frame_file(path: str | os.PathLike, *, trusted: bool = False) -> dict:
    """Load one metrical-tracker ``.frame`` file. Safe by default (weights-only unpickling: tensors, numpy arrays,
    containers, numbers, strings); ``trusted=True`` falls back to full unpickling, which can execute code."""
    path = Path(path)
    try:
        with torch.serialization.safe_globals(_NUMPY_SAFE_GLOBALS):
            data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        if not trusted:
            first = next((line.strip() for line in str(e).splitlines() if "Unsupported global" in line), "")
            raise DatasetError(
                f"needs full unpickling to load ({first or 'it holds objects other than tensors and arrays'}); "
                f"unpickling can run arbitrary code, so it is refused. Only for a folder you produced yourself, "
                f"pass trusted=True (CLI: --trusted)", field=str(path)) from None
        try:
            data = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e2:
            raise DatasetError(f"cannot load: {e2}", field=str(path)) from None
    except Exception as e:
        raise DatasetError(f"cannot load as a torch-saved file: {str(e).splitlines()[0] if str(e) else e!r}",
                           field=str(path)) from None
    if not isinstance(data, dict):
        raise DatasetError(f"expected a dict, got {type(data).__name__}", field=str(path))
    return data


def split_indices(n: int, test_frames: int = 350) -> tuple[np.ndarray, np.ndarray]:
    """Train/test split of a metrical-tracker sequence: the last ``test_frames`` frames are the test set when at
    least as many frames remain for training (n >= 2 test_frames); a shorter sequence holds out its last 15%
    (rounded, at least one frame when n >= 2); test_frames <= 0 or a single frame: no test set."""
    if test_frames <= 0 or n < 2:
        n_test = 0
    elif n >= 2 * test_frames:
        n_test = test_frames
    else:
        n_test = max(1, round(FALLBACK_TEST_FRACTION * n))
    return np.arange(n - n_test, dtype=np.int64), np.arange(n - n_test, n, dtype=np.int64)


def _matrix_to_axis_angle(m: torch.Tensor) -> torch.Tensor:
    q = matrix_to_quat(m)  # w >= 0, so the angle lies in [0, pi]
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    scale = torch.where(s > 1e-12, angle / s.clamp_min(1e-12), torch.full_like(s, 2.0))
    return v * scale


def _rotations(values: np.ndarray, count: int, field: str) -> torch.Tensor:
    """``count`` rotations stored as 6D (6 values each, the first two matrix rows) or axis-angle (3 each) ->
    axis-angle [count, 3]."""
    flat = torch.from_numpy(values.reshape(-1).astype(np.float64))
    if flat.numel() == 6 * count:
        return _matrix_to_axis_angle(rot6d_to_matrix(flat.reshape(count, 6)))
    if flat.numel() == 3 * count:
        return flat.reshape(count, 3)
    raise DatasetError(f"expected {count} rotations as 6D ({6 * count} values) or axis-angle ({3 * count}), "
                       f"got {flat.numel()} values", field=field)


def _array(data: dict, keys: tuple[str, ...], path: Path, sizes: tuple[int, ...] | None = None,
           optional: bool = False) -> np.ndarray | None:
    node = data
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            if optional:
                return None
            raise DatasetError(f"missing key {'.'.join(keys)!r}", field=str(path))
        node = node[key]
    field = f"{path}:{'.'.join(keys)}"
    if isinstance(node, torch.Tensor):
        node = node.detach().cpu().numpy()
    try:
        a = np.asarray(node)
    except Exception:
        raise DatasetError(f"not an array ({type(node).__name__})", field=field) from None
    if a.dtype.kind not in "fiu":
        raise DatasetError(f"expected numbers, got {a.dtype}", field=field)
    if sizes is not None and a.size not in sizes:
        raise DatasetError(f"expected {' or '.join(map(str, sizes))} values, got shape {list(a.shape)}", field=field)
    return a.astype(np.float64)


def _frame_key(path: Path):
    return (0, int(path.stem), path.stem) if path.stem.isdigit() else (1, 0, path.stem)


def read_metrical(folder: str | os.PathLike, n_expression: int = 50, test_frames: int = 350, *,
                  trusted: bool = False, fps: float = 30.0) -> tuple[Tracking, list[Path]]:
    """Read a metrical-tracker / INSTA subject folder: the tracking (face model "flame", expressions exp_00.. -
    the first ``n_expression`` FLAME components, joints root, neck, jaw, eye_l, eye_r with root and neck at
    identity because the head pose lives in the camera extrinsics) and the RGBA image of every tracked frame
    (``images/<stem>.png`` for ``checkpoint/<stem>.frame``). Frame order: numeric stems ascending. Split: see
    :func:`split_indices`. ``shape`` comes from the first frame. ``trusted``: see :func:`load_frame_file`."""
    folder = Path(folder)
    files = sorted((folder / "checkpoint").glob("*.frame"), key=_frame_key)
    if not files:
        raise DatasetError(f"no checkpoint/*.frame files in {folder}", field="checkpoint")
    if not 1 <= n_expression <= 100:
        raise DatasetError(f"must be in [1, 100] (FLAME expression components), got {n_expression}",
                           field="n_expression")
    images = [folder / "images" / f"{f.stem}.png" for f in files]
    missing = [str(p) for p in images if not p.is_file()]
    if missing:
        raise DatasetError(f"{len(missing)} tracked frames have no image: {', '.join(missing[:3])}"
                           f"{' ...' if len(missing) > 3 else ''}", field="images")
    first = read_image(images[0], str(images[0]), kind="rgba", width=None, height=None)
    height, width = first.shape[:2]

    n = len(files)
    expression = np.zeros((n, n_expression), np.float64)
    joints = np.zeros((n, len(JOINT_NAMES), 3), np.float64)
    eyelids = np.zeros((n, 2), np.float64)
    cam_k, cam_r, cam_t = np.zeros((n, 3, 3)), np.zeros((n, 3, 3)), np.zeros((n, 3))
    shape = np.zeros(0)
    for i, path in enumerate(files):
        data = load_frame_file(path, trusted=trusted)
        exp = _array(data, ("flame", "exp"), path).reshape(-1)
        if exp.size < n_expression:
            raise DatasetError(f"has {exp.size} expression coefficients, fewer than n_expression={n_expression}",
                               field=f"{path}:flame.exp")
        expression[i] = exp[:n_expression]
        joints[i, 2] = _rotations(_array(data, ("flame", "jaw"), path, (3, 6)), 1, f"{path}:flame.jaw").numpy()
        joints[i, 3:5] = _rotations(_array(data, ("flame", "eyes"), path, (6, 12)), 2, f"{path}:flame.eyes").numpy()
        lids = _array(data, ("flame", "eyelids"), path, (2,), optional=True)
        eyelids[i] = 0.0 if lids is None else lids.reshape(2)
        if i == 0:
            s = _array(data, ("flame", "shape"), path, optional=True)
            shape = np.zeros(0) if s is None else s.reshape(-1)
        cam_r[i] = _array(data, ("opencv", "R"), path, (9,)).reshape(3, 3)
        cam_t[i] = _array(data, ("opencv", "t"), path, (3,)).reshape(3)
        cam_k[i] = _array(data, ("opencv", "K"), path, (9,)).reshape(3, 3)
        size = _array(data, ("img_size",), path, (2,), optional=True)
        if size is not None:
            a, b = (int(round(v)) for v in size.reshape(2))
            if (a, b) not in ((height, width), (width, height)):
                raise DatasetError(f"img_size {a}x{b} does not match the images ({width}x{height}); K is given at "
                                   f"img_size", field=f"{path}:img_size")

    train, test = split_indices(n, test_frames)
    tracking = Tracking(
        face_model=FACE_MODEL, expression_names=[f"exp_{k:02d}" for k in range(n_expression)],
        joint_names=list(JOINT_NAMES), expression=expression.astype(np.float32),
        joint_rotations=joints.astype(np.float32), eyelids=eyelids.astype(np.float32),
        K=cam_k.astype(np.float32), R=cam_r.astype(np.float32), t=cam_t.astype(np.float32),
        shape=shape.astype(np.float32), train=train, test=test, width=int(width), height=int(height),
        fps=float(fps))
    check_tracking(tracking, str(folder))
    return tracking, images


class _Queue:
    """An iterator over values pushed by another iterator (the masks split off the RGBA images)."""

    def __init__(self):
        self.items: deque = deque()

    def __iter__(self):
        return self

    def __next__(self):
        if not self.items:
            raise StopIteration
        return self.items.popleft()


def convert_metrical(src: str | os.PathLike, out_dir: str | os.PathLike, *, n_expression: int = 50,
                     test_frames: int = 350, trusted: bool = False, fps: float = 30.0,
                     image_format: str = "png") -> Path:
    """Convert a metrical-tracker / INSTA folder to a portable dataset at ``out_dir``: frames are the images' RGB
    as stored (not composited or premultiplied), masks their alpha channel. Returns ``out_dir``."""
    tracking, images = read_metrical(src, n_expression, test_frames, trusted=trusted, fps=fps)
    masks = _Queue()

    def frames():
        for path in images:
            rgba = read_image(path, str(path), kind="rgba", width=tracking.width, height=tracking.height)
            masks.items.append(rgba[..., 3])
            yield rgba[..., :3]

    return write_dataset(out_dir, frames(), masks, tracking, image_format=image_format)
