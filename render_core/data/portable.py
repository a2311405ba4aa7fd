"""The portable tracked-video format (``blendsplat-tracked-video``, version 1): what uploads use.

A dataset is a folder with ``dataset.json`` (manifest), ``tracking.npz`` (per-frame face-model parameters and
cameras, loaded with ``allow_pickle=False``), the frames (PNG / JPEG / EXR files, or one video file) and the head
masks (PNG files). Nothing in it is ever executed or unpickled. The specification is
``docs/tracked-video-format.md``; this module writes, reads and validates it.

- :func:`write_dataset` writes one (into a temporary folder beside the target, then renamed).
- :func:`read_dataset` checks the manifest and the tracking (not every image) and returns a :class:`Dataset`.
- :func:`validate_dataset` reports every problem, each prefixed by the field or file it concerns.
- :func:`check_tracking` and :func:`read_image` are the checks that other readers (``metrical.py``) share.
"""

from __future__ import annotations

import json
import math
import os
import re
import secrets
import shutil
import stat
import zipfile
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..media.files import write_image
from ..media.pixels import to_uint8

FORMAT = "blendsplat-tracked-video"
VERSION = 1
MANIFEST = "dataset.json"
TRACKING = "tracking.npz"

# Limits (docs/tracked-video-format.md, "Limits").
MAX_SIDE = 8192
MAX_FRAMES = 200_000
MAX_EXPRESSIONS = 1024
MAX_JOINTS = 256
MAX_SHAPE = 4096
MAX_NAME_CHARS = 128
MAX_PATTERN_CHARS = 255
MAX_MANIFEST_BYTES = 1 << 20
MAX_TRACKING_BYTES = 1 << 30  # tracking.npz, uncompressed, all arrays together
MAX_IMAGE_BYTES = 256 << 20  # one frame or mask file
MAX_FPS = 1000.0
MAX_ABS_COEFFICIENT = 100.0  # expression coefficients and eyelids
MAX_ABS_TRANSLATION = 1000.0  # metres
MAX_JOINT_ANGLE = 2.0 * math.pi  # radians
ROTATION_TOLERANCE = 1e-3  # max |R R^T - I| and |det R - 1|

IMAGE_FORMATS = ("png", "jpeg", "exr", "mp4")  # write_dataset's image_format
FRAME_EXTENSIONS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".exr": "openexr"}
MASK_EXTENSIONS = {".png": "png"}
VIDEO_EXTENSIONS = (".mp4", ".mkv", ".mov", ".webm")
_MAGIC = {"png": b"\x89PNG\r\n\x1a\n", "jpeg": b"\xff\xd8\xff", "openexr": b"\x76\x2f\x31\x01"}
_KIND_NAMES = {"png": "PNG", "jpeg": "JPEG", "openexr": "OpenEXR"}
_CHANNELS = {1: "grey", 3: "RGB", 4: "RGBA"}

MANIFEST_KEYS = ("format", "version", "frames", "width", "height", "fps", "face_model", "frame_files", "video",
                 "mask_files")
FLOAT_ARRAYS = ("expression", "joint_rotations", "eyelids", "K", "R", "t", "shape")
INDEX_ARRAYS = ("train", "test")
NAME_ARRAYS = ("expression_names", "joint_names")
TRACKING_ARRAYS = ("expression", "expression_names", "joint_rotations", "joint_names", "eyelids", "K", "R", "t",
                   "shape", "train", "test")
_PER_FRAME = ("K", "R", "t", "expression", "joint_rotations", "eyelids")  # also the tie-break order for N

_PLACEHOLDER = re.compile(r"\{(?::(?:0[1-9])?d)?\}")
_SAFE_PATH = re.compile(r"[A-Za-z0-9_.-]+(?:/[A-Za-z0-9_.-]+)*")

Problem = tuple[str, str]  # (field, message)


# --------------------------------------------------------------------------------------------------------- tracking
@dataclass(eq=False)
class Tracking:
    """Per-frame face-model parameters and cameras of a tracked video (N frames), in the conventions of
    docs/tracked-video-format.md: metres, OpenCV cameras (x right, y down, z forward; world-to-camera R, t; K in
    pixels at width x height), axis-angle joint rotations relative to the parent in the parent's rest frame,
    expression coefficients in ``expression_names`` order."""

    face_model: str  # FaceModel.name the parameters refer to
    expression_names: list[str]  # K
    joint_names: list[str]  # J
    expression: np.ndarray  # [N, K] float32
    joint_rotations: np.ndarray  # [N, J, 3] float32 axis-angle
    eyelids: np.ndarray  # [N, 2] float32
    K: np.ndarray  # [N, 3, 3] float32
    R: np.ndarray  # [N, 3, 3] float32
    t: np.ndarray  # [N, 3] float32
    shape: np.ndarray  # [S] float32 (may be empty)
    train: np.ndarray  # int64 indices
    test: np.ndarray  # int64 indices
    width: int
    height: int
    fps: float = 30.0

    @property
    def frames(self) -> int:
        """N: the frame count most per-frame arrays agree on (0 if none is an array)."""
        return _frame_count(self)

    def validate(self) -> list[str]:
        """Every problem, each as ``"field: message"``; [] when the tracking is valid."""
        return [_fmt(p) for p in _tracking_problems(self)]

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``tracking.npz`` (names as unicode arrays)."""
        out = {name: getattr(self, name) for name in FLOAT_ARRAYS + INDEX_ARRAYS}
        out["expression_names"] = np.asarray(list(self.expression_names), dtype=np.str_).reshape(-1)
        out["joint_names"] = np.asarray(list(self.joint_names), dtype=np.str_).reshape(-1)
        return out


def _fmt(p: Problem) -> str:
    return f"{p[0]}: {p[1]}"


def _is_int(v) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool | np.bool_)


def _is_real(v) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool | np.bool_)


def _frames_text(idx) -> str:
    idx = [int(i) for i in np.asarray(idx).reshape(-1)]
    head = ", ".join(str(i) for i in idx[:5])
    return f"{head} (and {len(idx) - 5} more)" if len(idx) > 5 else head


def _frame_count(tr: Tracking) -> int:
    lead = [a.shape[0] for a in (getattr(tr, f, None) for f in _PER_FRAME) if isinstance(a, np.ndarray) and a.ndim]
    if not lead:
        return 0
    counts = Counter(lead)
    best = max(counts.values())
    return next(n for n in lead if counts[n] == best)  # ties: the first in _PER_FRAME order (cameras first)


def _names_problems(field: str, names, limit: int) -> tuple[list[Problem], list[str] | None]:
    if isinstance(names, np.ndarray):
        names = names.tolist() if names.ndim == 1 else None
    if not isinstance(names, list | tuple) or not all(isinstance(n, str) for n in names):
        return [(field, "must be a list of strings")], None
    out = []
    if not 1 <= len(names) <= limit:
        out.append((field, f"must hold 1 to {limit} names, got {len(names)}"))
    bad = [n for n in names if not n or len(n) > MAX_NAME_CHARS or not n.isprintable() or n != n.strip()]
    if bad:
        out.append((field, f"names must be 1 to {MAX_NAME_CHARS} printable characters without surrounding spaces: "
                           f"{', '.join(repr(n[:40]) for n in bad[:5])}"))
    repeated = sorted(n for n, c in Counter(names).items() if c > 1)
    if repeated:
        out.append((field, f"names repeat: {', '.join(repr(n) for n in repeated[:5])}"))
    return out, (list(names) if not out else None)


def _tracking_problems(tr: Tracking) -> list[Problem]:
    """Every problem of a tracking, in a fixed order: the scalars, the names, the arrays' dtypes, the frame count,
    the shapes, the values (finite, in range, rotations, intrinsics), the train/test split."""
    out = _scalar_problems(tr)
    expr_problems, expr_names = _names_problems("expression_names", tr.expression_names, MAX_EXPRESSIONS)
    joint_problems, joint_names = _names_problems("joint_names", tr.joint_names, MAX_JOINTS)
    out += expr_problems + joint_problems
    arrays, dtype_problems = _typed_arrays(tr)
    out += dtype_problems
    n = _frame_count(tr)
    if not 1 <= n <= MAX_FRAMES:
        out.append(("frames", f"the tracking must have 1 to {MAX_FRAMES} frames, got {n}"))
    k = len(expr_names) if expr_names is not None else None
    j = len(joint_names) if joint_names is not None else None
    good, shape_problems = _shaped_arrays(arrays, n, k, j)
    out += shape_problems
    out += _value_problems(good)
    out += _split_problems(arrays, n)
    return out


def _scalar_problems(tr: Tracking) -> list[Problem]:
    """The face model's name, the image size and the frame rate."""
    out: list[Problem] = []
    fm = tr.face_model
    if not isinstance(fm, str) or not fm or len(fm) > MAX_NAME_CHARS or not fm.isprintable():
        out.append(("face_model", f"must be a name of 1 to {MAX_NAME_CHARS} printable characters, got {fm!r}"))
    for name in ("width", "height"):
        v = getattr(tr, name)
        if not _is_int(v) or not 1 <= v <= MAX_SIDE:
            out.append((name, f"must be an integer in [1, {MAX_SIDE}] (pixels), got {v!r}"))
    if not _is_real(tr.fps) or not math.isfinite(tr.fps) or not 0 < tr.fps <= MAX_FPS:
        out.append(("fps", f"must be a number in (0, {MAX_FPS:g}], got {tr.fps!r}"))
    return out


def _typed_arrays(tr: Tracking) -> tuple[dict[str, np.ndarray], list[Problem]]:
    """The float and index arrays that are numpy arrays of their file dtype, and a problem for each other one."""
    arrays: dict[str, np.ndarray] = {}
    out: list[Problem] = []
    for name in FLOAT_ARRAYS + INDEX_ARRAYS:
        a = getattr(tr, name)
        want = np.float32 if name in FLOAT_ARRAYS else np.int64
        if not isinstance(a, np.ndarray):
            out.append((name, f"must be a numpy array, got {type(a).__name__}"))
        elif a.dtype != want:
            out.append((name, f"dtype must be {np.dtype(want).name}, got {a.dtype}"))
        else:
            arrays[name] = a
    return arrays, out


def _shaped_arrays(arrays: dict[str, np.ndarray], n: int, k: int | None,
                   j: int | None) -> tuple[dict[str, np.ndarray], list[Problem]]:
    """The per-frame arrays (and ``shape``) of the expected shapes for N frames, K expressions and J joints (None:
    unknown, any size), and a problem for each other one."""
    out: list[Problem] = []
    expected = {"expression": (("N", n), ("K", k)), "joint_rotations": (("N", n), ("J", j), ("", 3)),
                "eyelids": (("N", n), ("", 2)), "K": (("N", n), ("", 3), ("", 3)),
                "R": (("N", n), ("", 3), ("", 3)), "t": (("N", n), ("", 3))}
    good: dict[str, np.ndarray] = {}
    for name, dims in expected.items():
        a = arrays.get(name)
        if a is None:
            continue
        ok = a.ndim == len(dims) and all(want is None or got == want for got, (_, want) in zip(a.shape, dims,
                                                                                               strict=False))
        if ok:
            good[name] = a
            continue
        sym = ", ".join(s or str(v) for s, v in dims)
        val = ", ".join("?" if v is None else str(v) for _, v in dims)
        out.append((name, f"expected shape [{sym}] = [{val}], got {list(a.shape)}"))
    if "shape" in arrays:
        s = arrays["shape"]
        if s.ndim != 1 or s.shape[0] > MAX_SHAPE:
            out.append(("shape", f"expected a 1-D array of at most {MAX_SHAPE} identity coefficients, got "
                                 f"{list(s.shape)}"))
        else:
            good["shape"] = s
    return good, out


def _value_problems(good: dict[str, np.ndarray]) -> list[Problem]:
    """Non-finite values in well-shaped arrays, then the ranges of the finite ones: coefficients, joint angles,
    translations, pinhole intrinsics, rotation matrices."""
    out: list[Problem] = []
    finite: dict[str, np.ndarray] = {}
    for name, a in good.items():
        bad = ~np.isfinite(a)
        if bad.any():
            where = f" at frames {_frames_text(np.nonzero(bad.reshape(len(a), -1).any(1))[0])}" if name != "shape" \
                else ""
            out.append((name, f"{int(bad.sum())} non-finite values (NaN/Inf){where}"))
        else:
            finite[name] = a
    for name in ("expression", "eyelids"):
        a = finite.get(name)
        if a is not None and a.size and np.abs(a).max() > MAX_ABS_COEFFICIENT:
            rows = np.nonzero((np.abs(a) > MAX_ABS_COEFFICIENT).any(1))[0]
            out.append((name, f"|value| exceeds {MAX_ABS_COEFFICIENT:g} at frames {_frames_text(rows)}"))
    if "joint_rotations" in finite and finite["joint_rotations"].size:
        angle = np.linalg.norm(finite["joint_rotations"].astype(np.float64), axis=-1)
        rows = np.nonzero((angle > MAX_JOINT_ANGLE).any(1))[0]
        if len(rows):
            out.append(("joint_rotations",
                        f"rotation angles exceed 2 pi (axis-angle norm) at frames {_frames_text(rows)}"))
    if "t" in finite:
        rows = np.nonzero((np.abs(finite["t"]) > MAX_ABS_TRANSLATION).any(1))[0]
        if len(rows):
            out.append(("t", f"|translation| exceeds {MAX_ABS_TRANSLATION:g} m at frames {_frames_text(rows)}"))
    if "K" in finite:
        out += _intrinsics_problems(finite["K"])
    if "R" in finite:
        r = finite["R"].astype(np.float64)
        err = np.abs(r @ r.transpose(0, 2, 1) - np.eye(3)).max((1, 2))
        det = np.linalg.det(r) if len(r) else np.zeros(0)
        rows = np.nonzero((err > ROTATION_TOLERANCE) | (np.abs(det - 1.0) > ROTATION_TOLERANCE))[0]
        if len(rows):
            out.append(("R", f"not a rotation matrix (orthonormal, det +1, tolerance {ROTATION_TOLERANCE:g}) at "
                             f"frames {_frames_text(rows)}"))
    return out


def _intrinsics_problems(k: np.ndarray) -> list[Problem]:
    """Finite ``K [N, 3, 3]`` that are not pinhole matrices with positive focal lengths."""
    out: list[Problem] = []
    kk = k.astype(np.float64)
    fixed = np.abs(kk[:, 2] - [0.0, 0.0, 1.0]).max(1) + np.abs(kk[:, 1, 0]) + np.abs(kk[:, 0, 1])
    rows = np.nonzero(fixed > 1e-6)[0]
    if len(rows):
        out.append(("K", f"not a pinhole intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] at frames "
                         f"{_frames_text(rows)}"))
    rows = np.nonzero((kk[:, 0, 0] <= 0) | (kk[:, 1, 1] <= 0))[0]
    if len(rows):
        out.append(("K", f"focal lengths fx, fy must be positive (pixels) at frames {_frames_text(rows)}"))
    return out


def _split_problems(arrays: dict[str, np.ndarray], n: int) -> list[Problem]:
    """The train and test indices: 1-D, in [0, n), unique, train not empty, disjoint and together every frame."""
    out: list[Problem] = []
    split: dict[str, np.ndarray] = {}
    for name in INDEX_ARRAYS:
        a = arrays.get(name)
        if a is None:
            continue
        if a.ndim != 1:
            out.append((name, f"expected a 1-D array of frame indices, got shape {list(a.shape)}"))
            continue
        problem = False
        if n >= 1 and a.size and (a.min() < 0 or a.max() >= n):
            out.append((name, f"frame indices must lie in [0, {n}), got {_frames_text(a[(a < 0) | (a >= n)])}"))
            problem = True
        values, counts = np.unique(a, return_counts=True)
        if (counts > 1).any():
            out.append((name, f"frame indices repeat: {_frames_text(values[counts > 1])}"))
            problem = True
        if not problem:
            split[name] = a
    if "train" in split and not split["train"].size:
        out.append(("train", "the training set is empty"))
    if len(split) == 2:
        both = np.intersect1d(split["train"], split["test"])
        if both.size:
            out.append(("test", f"train and test overlap at frames {_frames_text(both)}"))
        elif 1 <= n <= MAX_FRAMES:
            missing = np.setdiff1d(np.arange(n), np.concatenate([split["train"], split["test"]]))
            if missing.size:
                out.append(("train",
                            f"train and test together must cover every frame; missing {_frames_text(missing)}"))
    return out


def _coerced(tr: Tracking) -> Tracking:
    """A copy with the file dtypes (float32 arrays, int64 indices, lists of names) where that is lossless in kind;
    anything else is left for validate() to report."""

    def cast(a, dtype, kinds: str):
        try:
            b = np.asarray(a)
        except Exception:
            return a
        return b.astype(dtype) if b.dtype.kind in kinds else b

    def floats(a):
        return cast(a, np.float32, "fiu")

    def indices(a):
        return cast(a, np.int64, "iu")

    def names(v):
        if isinstance(v, np.ndarray) and v.ndim == 1 and v.dtype.kind == "U":
            return [str(x) for x in v]
        return list(v) if isinstance(v, list | tuple) else v

    return Tracking(
        face_model=tr.face_model, expression_names=names(tr.expression_names), joint_names=names(tr.joint_names),
        expression=floats(tr.expression), joint_rotations=floats(tr.joint_rotations), eyelids=floats(tr.eyelids),
        K=floats(tr.K), R=floats(tr.R), t=floats(tr.t), shape=floats(tr.shape), train=indices(tr.train),
        test=indices(tr.test), width=int(tr.width) if _is_int(tr.width) else tr.width,
        height=int(tr.height) if _is_int(tr.height) else tr.height,
        fps=float(tr.fps) if _is_real(tr.fps) else tr.fps)


def _raise(problems: list[Problem], what: str) -> None:
    if not problems:
        return
    f, m = problems[0]
    more = f" (and {len(problems) - 1} more: {'; '.join(_fmt(p) for p in problems[1:6])}" \
           f"{'; ...' if len(problems) > 6 else ''})" if len(problems) > 1 else ""
    raise DatasetError(f"{m}{more} [{what}]", field=f)


def check_tracking(tracking: Tracking, what: str) -> None:
    """Raise DatasetError naming the first problem of ``tracking`` (its message lists the others and ends with
    ``[what]``, where the tracking came from); return when it is valid. :meth:`Tracking.validate` lists them."""
    _raise(_tracking_problems(tracking), what)


# ------------------------------------------------------------------------------------------------------- images
def _oiio():
    import OpenImageIO as oiio

    return oiio


def _regular_file(path: Path, root: Path | None) -> str | None:
    """None if ``path`` is a regular file inside ``root`` (after resolving links), else what is wrong."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "missing"
    except OSError as e:
        return f"cannot stat: {e.strerror or e}"
    if not stat.S_ISREG(st.st_mode):
        return "not a regular file"
    if root is not None and not path.resolve().is_relative_to(root.resolve()):
        return "resolves outside the dataset folder (a link)"
    return None


def _message(e: DatasetError) -> str:
    """The message of a DatasetError without its ``field: `` prefix."""
    text = str(e)
    return text[len(e.field) + 2:] if e.field and text.startswith(f"{e.field}: ") else text


def read_image(path: Path, rel: str, *, kind: str, width: int | None, height: int | None,
                root: Path | None = None) -> np.ndarray:
    """Decode one image fully: kind "frame" (3 channels; PNG/JPEG 8-bit or EXR half/float), "mask" (1-channel 8-bit
    PNG) or "rgba" (4-channel 8-bit PNG, unassociated alpha). Raises DatasetError(field=rel) naming what is wrong.
    Returns uint8 [H, W, C] (masks [H, W]) or float32 for EXR."""
    why = _regular_file(path, root)
    if why:
        raise DatasetError(why, field=rel)
    table = FRAME_EXTENSIONS if kind == "frame" else MASK_EXTENSIONS
    fmt = table.get(path.suffix.lower())
    if fmt is None:
        raise DatasetError(f"unsupported extension {path.suffix!r}; use {', '.join(table)}", field=rel)
    size = path.stat().st_size
    if size > MAX_IMAGE_BYTES:
        raise DatasetError(f"file of {size} bytes exceeds the limit of {MAX_IMAGE_BYTES}", field=rel)
    with open(path, "rb") as fh:
        head = fh.read(8)
    if not head.startswith(_MAGIC[fmt]):
        raise DatasetError(f"not a {_KIND_NAMES[fmt]} file (its first bytes do not match)", field=rel)
    oiio = _oiio()
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # RGB as stored, not premultiplied by the alpha
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise DatasetError(f"cannot decode: {_oneline(oiio.geterror())}", field=rel)
    try:
        if inp.format_name() != fmt:
            raise DatasetError(f"decodes as {inp.format_name()}, not {_KIND_NAMES[fmt]}", field=rel)
        spec = inp.spec()
        if spec.deep:
            raise DatasetError("deep images are not supported", field=rel)
        if (width is not None and spec.width != width) or (height is not None and spec.height != height):
            raise DatasetError(f"size {spec.width}x{spec.height}, expected {width}x{height}", field=rel)
        if not 1 <= spec.width <= MAX_SIDE or not 1 <= spec.height <= MAX_SIDE:
            raise DatasetError(f"size {spec.width}x{spec.height} exceeds the limit of {MAX_SIDE}", field=rel)
        want = {"frame": 3, "mask": 1, "rgba": 4}[kind]
        if spec.nchannels != want:
            raise DatasetError(f"{spec.nchannels} channels, expected {want} ({_CHANNELS[want]})", field=rel)
        if fmt == "openexr":
            if str(spec.format) not in ("half", "float"):
                raise DatasetError(f"EXR pixels must be half or float, got {spec.format}", field=rel)
            out_type = oiio.FLOAT
        else:
            if str(spec.format) != "uint8":
                raise DatasetError(f"pixels must be 8-bit, got {spec.format}", field=rel)
            out_type = oiio.UINT8
        pixels = inp.read_image(0, 0, 0, want, out_type)
        if pixels is None:
            raise DatasetError(f"cannot decode (truncated or corrupt): {_oneline(inp.geterror())}", field=rel)
        pixels = np.asarray(pixels).reshape(spec.height, spec.width, want)
        if fmt == "openexr" and not np.isfinite(pixels).all():
            raise DatasetError("non-finite pixel values (NaN/Inf)", field=rel)
        return pixels[..., 0] if kind == "mask" else pixels
    finally:
        inp.close()
        oiio.geterror()  # clear any pending message so OpenImageIO does not print it at exit


def _oneline(text: str) -> str:
    text = " / ".join(line.strip() for line in (text or "").splitlines() if line.strip())
    return text[:500] or "unknown error"


# -------------------------------------------------------------------------------------------------------- video
def _iter_video(path: Path, rel: str, *, width: int | None, height: int | None, limit: int,
                root: Path | None = None) -> Iterator[np.ndarray]:
    """Decode a video file's first video stream to uint8 RGB frames, at most ``limit`` + 1 of them; raises
    DatasetError(field=rel) on any decoding problem or a frame of the wrong size."""
    why = _regular_file(path, root)
    if why:
        raise DatasetError(why, field=rel)
    import av

    try:
        container = av.open(str(path), mode="r")
    except Exception as e:  # PyAV raises many error types for hostile input
        raise DatasetError(f"cannot open as a video: {_oneline(str(e))}", field=rel) from None
    try:
        if not container.streams.video:
            raise DatasetError("contains no video stream", field=rel)
        stream = container.streams.video[0]
        count = 0
        try:
            for frame in container.decode(stream):
                if (width is not None and frame.width != width) or (height is not None and frame.height != height):
                    raise DatasetError(f"frame {count} is {frame.width}x{frame.height}, expected {width}x{height}",
                                       field=rel)
                yield frame.to_ndarray(format="rgb24")
                count += 1
                if count > limit:
                    return
        except DatasetError:
            raise
        except Exception as e:
            raise DatasetError(f"cannot decode frame {count}: {_oneline(str(e))}", field=rel) from None
    finally:
        container.close()


def _write_video(path: Path, frames: Iterator[np.ndarray], fps: float, width: int, height: int) -> None:
    """Lossless H.264 (libx264rgb, RGB 4:4:4, crf 0) in an MP4 container."""
    import av

    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264rgb", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = width, height
        stream.pix_fmt = "rgb24"
        stream.options = {"crf": "0", "preset": "medium"}
        for rgb in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


# ----------------------------------------------------------------------------------------------------- manifest
def _pattern_problem(value, allowed: dict[str, str]) -> str | None:
    if not isinstance(value, str):
        return f"must be a string file pattern such as 'frames/{{:05d}}.png', got {type(value).__name__}"
    if len(value) > MAX_PATTERN_CHARS:
        return f"longer than {MAX_PATTERN_CHARS} characters"
    if len(_PLACEHOLDER.findall(value)) != 1:
        return f"must contain exactly one frame-number placeholder ({{:05d}}, {{:d}} or {{}}), got {value!r}"
    sample = _PLACEHOLDER.sub("0", value)
    if not _SAFE_PATH.fullmatch(sample) or any(part in (".", "..") for part in sample.split("/")):
        return (f"must be a relative path of letters, digits, '_', '-', '.' and '/' with no '.' or '..' "
                f"components, got {value!r}")
    ext = os.path.splitext(sample)[1].lower()
    if ext not in allowed:
        return f"extension {ext!r} is not one of {', '.join(allowed)}"
    return None


def _manifest_problems(manifest) -> list[Problem]:
    """Structure of dataset.json. Values that the tracking also carries (width, height, fps, face_model) are only
    checked for presence here; Tracking.validate checks them."""
    if not isinstance(manifest, dict):
        return [(MANIFEST, "must hold a JSON object")]
    out: list[Problem] = []
    for key in manifest:
        if key not in MANIFEST_KEYS:
            out.append((str(key)[:60], f"unknown key in {MANIFEST} (version {VERSION} defines "
                                       f"{', '.join(MANIFEST_KEYS)})"))
    for key in ("format", "version", "frames", "width", "height", "fps", "face_model", "mask_files"):
        if key not in manifest:
            out.append((key, f"missing from {MANIFEST}"))
    if "format" in manifest and manifest["format"] != FORMAT:
        out.append(("format", f"expected {FORMAT!r}, got {str(manifest['format'])[:80]!r}"))
    if "version" in manifest:
        v = manifest["version"]
        if not _is_int(v):
            out.append(("version", f"must be an integer, got {v!r}"[:200]))
        elif v != VERSION:
            out.append(("version", f"version {v} is not supported (this reader reads version {VERSION})"))
    if "frames" in manifest:
        v = manifest["frames"]
        if not _is_int(v) or not 1 <= v <= MAX_FRAMES:
            out.append(("frames", f"must be an integer in [1, {MAX_FRAMES}], got {v!r}"[:200]))
    has_files, has_video = "frame_files" in manifest, "video" in manifest
    if has_files == has_video:
        out.append(("frame_files", f"exactly one of 'frame_files' (a file pattern) and 'video' (a file name) must "
                                   f"be given, got {'both' if has_files else 'neither'}"))
    if has_files:
        why = _pattern_problem(manifest["frame_files"], FRAME_EXTENSIONS)
        if why:
            out.append(("frame_files", why))
    if has_video:
        v = manifest["video"]
        if not isinstance(v, str) or len(v) > MAX_PATTERN_CHARS or not _SAFE_PATH.fullmatch(v) \
                or any(part in (".", "..") for part in v.split("/")):
            out.append(("video", f"must be a relative file path of letters, digits, '_', '-', '.' and '/', "
                                 f"got {v!r}"[:200]))
        elif os.path.splitext(v)[1].lower() not in VIDEO_EXTENSIONS:
            out.append(("video", f"extension must be one of {', '.join(VIDEO_EXTENSIONS)}, got {v!r}"))
    if "mask_files" in manifest:
        why = _pattern_problem(manifest["mask_files"], MASK_EXTENSIONS)
        if why:
            out.append(("mask_files", why))
    return out


def _load_manifest(root: Path) -> tuple[dict | None, list[Problem]]:
    path = root / MANIFEST
    why = _regular_file(path, root)
    if why:
        return None, [(MANIFEST, why)]
    size = path.stat().st_size
    if size > MAX_MANIFEST_BYTES:
        return None, [(MANIFEST, f"{size} bytes exceeds the limit of {MAX_MANIFEST_BYTES}")]
    try:
        manifest = json.loads(path.read_bytes().decode("utf-8"))
    except (ValueError, RecursionError) as e:  # UnicodeDecodeError, JSONDecodeError, an over-long integer
        return None, [(MANIFEST, f"not valid UTF-8 JSON: {_oneline(str(e))}")]
    problems = _manifest_problems(manifest)
    return (manifest if isinstance(manifest, dict) else None), problems


# ----------------------------------------------------------------------------------------------------- tracking file
def _load_tracking_arrays(root: Path) -> tuple[dict[str, np.ndarray], list[Problem]]:
    """The arrays of tracking.npz that load safely (numeric or unicode, never objects), and the problems."""
    path = root / TRACKING
    why = _regular_file(path, root)
    if why:
        return {}, [(TRACKING, why)]
    size = path.stat().st_size
    if size > MAX_TRACKING_BYTES:
        return {}, [(TRACKING, f"{size} bytes exceeds the limit of {MAX_TRACKING_BYTES}")]
    out: list[Problem] = []
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            if len(infos) > 4 * len(TRACKING_ARRAYS):
                return {}, [(TRACKING, f"holds {len(infos)} members; version {VERSION} defines "
                                       f"{len(TRACKING_ARRAYS)} arrays")]
            total = sum(i.file_size for i in infos)
            if total > MAX_TRACKING_BYTES:
                return {}, [(TRACKING, f"{total} bytes uncompressed exceeds the limit of {MAX_TRACKING_BYTES}")]
            names = [i.filename for i in infos]
            for name, count in Counter(names).items():
                if count > 1:
                    out.append((TRACKING, f"member {name!r} appears {count} times"))
            present = []
            for info in infos:
                key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                if key not in TRACKING_ARRAYS:
                    out.append((key[:60], f"unknown array in {TRACKING} (version {VERSION} defines "
                                          f"{', '.join(TRACKING_ARRAYS)})"))
                    continue
                if not info.filename.endswith(".npy"):
                    out.append((key, f"member {info.filename!r} of {TRACKING} is not an .npy array"))
                    continue
                # Read the .npy header ourselves: refuse object arrays before numpy sees them, and refuse a
                # declared size larger than the member (numpy would allocate it first).
                try:
                    with zf.open(info) as fh:
                        major, _ = np.lib.format.read_magic(fh)
                        if major == 1:
                            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                        else:
                            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
                except Exception as e:
                    out.append((key, f"not a readable .npy array: {_oneline(str(e))}"))
                    continue
                if dtype.hasobject:
                    out.append((key, "is an object array; refused (loading it would need unpickling)"))
                    continue
                if math.prod(shape) * dtype.itemsize > info.file_size:
                    out.append((key, f"declares shape {list(shape)} of {dtype} but the member holds only "
                                     f"{info.file_size} bytes"))
                    continue
                present.append(key)
    except Exception as e:  # BadZipFile, OSError, EOFError, NotImplementedError (compression), ...
        return {}, out + [(TRACKING, f"not a readable .npz (zip) file: {_oneline(str(e))}")]
    arrays: dict[str, np.ndarray] = {}
    try:
        with np.load(path, allow_pickle=False) as npz:
            for key in present:
                try:
                    a = npz[key]
                except ValueError as e:
                    if "allow_pickle" in str(e):
                        out.append((key, "is an object array; refused (loading it would need unpickling)"))
                    else:
                        out.append((key, f"unreadable: {_oneline(str(e))}"))
                    continue
                except Exception as e:
                    out.append((key, f"unreadable: {_oneline(str(e))}"))
                    continue
                if not isinstance(a, np.ndarray):
                    out.append((key, "is not an array"))
                    continue
                if a.dtype.kind not in "fiuU":
                    out.append((key, f"dtype {a.dtype} is not allowed (float32, int64 or unicode)"))
                    continue
                arrays[key] = a
    except Exception as e:
        out.append((TRACKING, f"not a readable .npz file: {_oneline(str(e))}"))
    for key in TRACKING_ARRAYS:
        if key not in arrays and not any(f == key for f, _ in out):
            out.append((key, f"missing from {TRACKING}"))
    return arrays, out


def _tracking_from(arrays: dict[str, np.ndarray], manifest: dict | None) -> tuple[Tracking, list[Problem]]:
    out: list[Problem] = []
    names = {}
    for key in NAME_ARRAYS:
        a = arrays.get(key)
        if a is None:
            names[key] = None
        elif a.dtype.kind != "U" or a.ndim != 1:
            out.append((key, f"must be a 1-D unicode array, got {a.dtype} of shape {list(a.shape)}"))
            names[key] = None
        else:
            names[key] = [str(x) for x in a]
    m = manifest or {}
    tr = Tracking(face_model=m.get("face_model"), expression_names=names["expression_names"],
                  joint_names=names["joint_names"], **{k: arrays.get(k) for k in FLOAT_ARRAYS + INDEX_ARRAYS},
                  width=m.get("width"), height=m.get("height"), fps=m.get("fps"))
    return tr, out


# ------------------------------------------------------------------------------------------------------ dataset
class Dataset:
    """A portable tracked-video dataset opened by :func:`read_dataset`: the tracking and the frames/masks, decoded
    on demand (a video is decoded once, on the first frame() call, and kept in memory as uint8)."""

    def __init__(self, root: Path, tracking: Tracking, manifest: dict):
        self.root = root
        self.tracking = tracking
        self.manifest = manifest
        self._video: list[np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self.manifest["frames"])

    def __repr__(self) -> str:
        return (f"Dataset({str(self.root)!r}, frames={len(self)}, {self.tracking.width}x{self.tracking.height}, "
                f"face_model={self.tracking.face_model!r})")

    def _index(self, i: int) -> int:
        if not _is_int(i) or not 0 <= i < len(self):
            raise IndexError(f"frame index {i!r} out of range [0, {len(self)})")
        return int(i)

    def frame_path(self, i: int) -> Path | None:
        """The frame's file, or None when the frames are a video."""
        i = self._index(i)
        pattern = self.manifest.get("frame_files")
        return None if pattern is None else self.root / pattern.format(i)

    def frame(self, i: int) -> np.ndarray:
        """[H, W, 3] float32 in [0, 1]."""
        i = self._index(i)
        tr = self.tracking
        if "video" in self.manifest:
            if self._video is None:
                rel = self.manifest["video"]
                frames = list(_iter_video(self.root / rel, rel, width=tr.width, height=tr.height, limit=len(self),
                                          root=self.root))
                if len(frames) != len(self):
                    raise DatasetError(f"has {'more than ' if len(frames) > len(self) else ''}"
                                       f"{min(len(frames), len(self))} frames, expected {len(self)}", field=rel)
                self._video = frames
            return self._video[i].astype(np.float32) / 255.0
        rel = self.manifest["frame_files"].format(i)
        px = read_image(self.root / rel, rel, kind="frame", width=tr.width, height=tr.height, root=self.root)
        if px.dtype == np.uint8:
            return px.astype(np.float32) / 255.0
        return np.clip(px, 0.0, 1.0).astype(np.float32)

    def mask(self, i: int) -> np.ndarray:
        """[H, W] float32 in [0, 1] (1 = head / foreground)."""
        rel = self.manifest["mask_files"].format(self._index(i))
        px = read_image(self.root / rel, rel, kind="mask", width=self.tracking.width, height=self.tracking.height,
                         root=self.root)
        return px.astype(np.float32) / 255.0


def _inspect(root: Path) -> tuple[dict | None, Tracking | None, list[Problem]]:
    """Manifest + tracking checks (no image decoding)."""
    if not root.is_dir():
        return None, None, [(str(root), "not a dataset folder (no such directory)" if not root.exists()
                             else "not a dataset folder (not a directory)")]
    manifest, problems = _load_manifest(root)
    arrays, tracking_problems = _load_tracking_arrays(root)
    problems += tracking_problems
    tracking, more = _tracking_from(arrays, manifest)
    problems += more
    reported = {f for f, _ in problems}
    if manifest is None:  # its values are unknown, not wrong
        reported |= {"face_model", "width", "height", "fps"}
    if not arrays and TRACKING in reported:  # no array could be read: do not list each as wrong
        reported |= {*TRACKING_ARRAYS, "frames"}
    problems += [p for p in _tracking_problems(tracking) if p[0] not in reported]
    if manifest is not None and _is_int(manifest.get("frames")):
        n = tracking.frames
        if n and manifest["frames"] != n and "frames" not in reported:
            problems.append(("frames", f"{MANIFEST} says {manifest['frames']} frames but {TRACKING} has {n}"))
    return manifest, tracking, problems


def _expected_size(tracking: Tracking | None) -> tuple[int | None, int | None]:
    if tracking is None:
        return None, None
    w = tracking.width if _is_int(tracking.width) and 1 <= tracking.width <= MAX_SIDE else None
    h = tracking.height if _is_int(tracking.height) and 1 <= tracking.height <= MAX_SIDE else None
    return w, h


def _file_problems(root: Path, manifest: dict | None, tracking: Tracking | None, *, decode: bool) -> list[Problem]:
    """Every frame and mask file exists (decode=False) or decodes to the right size and channels (decode=True)."""
    if manifest is None:
        return []
    reported = {f for f, _ in _manifest_problems(manifest)}
    n = manifest.get("frames") if "frames" not in reported else (tracking.frames if tracking else 0)
    if not _is_int(n) or not 1 <= n <= MAX_FRAMES:
        return []
    width, height = _expected_size(tracking)
    out: list[Problem] = []
    if "video" in manifest and "video" not in reported and "frame_files" not in reported:
        rel = manifest["video"]
        if not decode:
            why = _regular_file(root / rel, root)
            if why:
                out.append((rel, why))
        else:
            count = 0
            try:
                for _ in _iter_video(root / rel, rel, width=width, height=height, limit=n, root=root):
                    count += 1
                if count != n:
                    out.append((rel, f"has {'more than ' if count > n else ''}{min(count, n)} frames, "
                                     f"expected {n}"))
            except DatasetError as e:
                out.append((e.field or rel, _message(e)))
    patterns = []
    if "frame_files" in manifest and "frame_files" not in reported and "video" not in manifest:
        patterns.append(("frame", manifest["frame_files"]))
    if "mask_files" not in reported:
        patterns.append(("mask", manifest["mask_files"]))
    for kind, pattern in patterns:
        for i in range(n):
            rel = pattern.format(i)
            if not decode:
                why = _regular_file(root / rel, root)
                if why:
                    out.append((rel, why))
                continue
            try:
                read_image(root / rel, rel, kind=kind, width=width, height=height, root=root)
            except DatasetError as e:
                out.append((rel, _message(e)))
    return out


def read_dataset(path: str | os.PathLike) -> Dataset:
    """Open a portable dataset: the manifest and the tracking are fully checked, the frame and mask files only for
    existence (use :func:`validate_dataset` to decode every one). Raises DatasetError naming the first offending
    field (its message lists the others)."""
    root = Path(path)
    manifest, tracking, problems = _inspect(root)
    if not problems:
        problems = _file_problems(root, manifest, tracking, decode=False)
    _raise(problems, str(root))
    return Dataset(root, tracking, manifest)


def validate_dataset(path: str | os.PathLike) -> list[str]:
    """Every problem of a dataset folder, each as ``"field or file: message"``; [] when it is valid. Checks the
    manifest, the tracking (shapes, counts, NaN/Inf, rotations, intrinsics, split) and decodes every frame and mask
    (size and channel count; a truncated or corrupt file is reported with its path)."""
    root = Path(path)
    manifest, tracking, problems = _inspect(root)
    problems += _file_problems(root, manifest, tracking, decode=True)
    return [_fmt(p) for p in problems]


# ------------------------------------------------------------------------------------------------------- writer
def _as_uint8(a, what: str, channels: int) -> np.ndarray:
    a = np.asarray(a)
    if channels == 1 and a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    want_ndim = 3 if channels == 3 else 2
    if a.ndim != want_ndim or (channels == 3 and a.shape[2] != 3):
        raise DatasetError(f"expected shape {'[H, W, 3]' if channels == 3 else '[H, W]'}, got {list(a.shape)}",
                           field=what)
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    if a.dtype.kind == "f":
        if not np.isfinite(a).all():
            raise DatasetError("non-finite values", field=what)
        return to_uint8(a)
    raise DatasetError(f"dtype must be uint8 (or float in [0, 1]), got {a.dtype}", field=what)


_END = object()


def write_dataset(out_dir: str | os.PathLike, frames: Iterable[np.ndarray], masks: Iterable[np.ndarray],
                  tracking: Tracking, image_format: str = "png") -> Path:
    """Write a portable dataset to ``out_dir`` and return its path.

    ``frames``: N uint8 [H, W, 3] RGB arrays (float in [0, 1] is accepted and rounded); ``masks``: N uint8 [H, W]
    (255 = head; bool or float in [0, 1] accepted); N, H and W from ``tracking``. ``image_format``: "png" (lossless),
    "jpeg" (quality 95, 4:4:4), "exr" (float32, value = byte / 255) or "mp4" (one lossless H.264 RGB video,
    ``frames.mp4``). Masks are always PNG. The tracking is validated first (float arrays are cast to float32 and
    indices to int64). Everything is written into a temporary folder beside ``out_dir`` and renamed into place;
    an existing non-empty ``out_dir`` is refused."""
    out_dir = Path(out_dir)
    fmt = {"jpg": "jpeg"}.get(str(image_format).lower(), str(image_format).lower())
    if fmt not in IMAGE_FORMATS:
        raise DatasetError(f"unsupported image format {image_format!r}; use one of {', '.join(IMAGE_FORMATS)}",
                           field="image_format")
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise DatasetError(f"{out_dir} exists and is not an empty folder; refusing to overwrite it", field="out_dir")
    tracking = _coerced(tracking)
    check_tracking(tracking, "tracking")
    n, width, height = tracking.frames, tracking.width, tracking.height

    manifest = {"format": FORMAT, "version": VERSION, "frames": n, "width": width, "height": height,
                "fps": tracking.fps, "face_model": tracking.face_model}
    ext = {"png": ".png", "jpeg": ".jpg", "exr": ".exr"}.get(fmt)
    if fmt == "mp4":
        manifest["video"] = "frames.mp4"
    else:
        manifest["frame_files"] = f"frames/{{:05d}}{ext}"
    manifest["mask_files"] = "masks/{:05d}.png"

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.{secrets.token_hex(6)}.tmp"
    tmp.mkdir()
    try:
        (tmp / "masks").mkdir()
        if fmt != "mp4":
            (tmp / "frames").mkdir()
        frame_iter, mask_iter = iter(frames), iter(masks)

        def checked_frames() -> Iterator[np.ndarray]:
            for i in range(n):
                rgb = next(frame_iter, _END)
                if rgb is _END:
                    raise DatasetError(f"got {i} frames, the tracking has {n}", field="frames")
                rgb = _as_uint8(rgb, f"frames[{i}]", 3)
                if rgb.shape[:2] != (height, width):
                    raise DatasetError(f"size {rgb.shape[1]}x{rgb.shape[0]}, expected {width}x{height}",
                                       field=f"frames[{i}]")
                yield rgb
                mask = next(mask_iter, _END)
                if mask is _END:
                    raise DatasetError(f"got {i} masks, the tracking has {n}", field="masks")
                mask = _as_uint8(mask, f"masks[{i}]", 1)
                if mask.shape != (height, width):
                    raise DatasetError(f"size {mask.shape[1]}x{mask.shape[0]}, expected {width}x{height}",
                                       field=f"masks[{i}]")
                write_image(tmp / manifest["mask_files"].format(i), mask)
            if next(frame_iter, _END) is not _END:
                raise DatasetError(f"more frames than the tracking's {n}", field="frames")
            if next(mask_iter, _END) is not _END:
                raise DatasetError(f"more masks than the tracking's {n}", field="masks")

        if fmt == "mp4":
            _write_video(tmp / manifest["video"], checked_frames(), tracking.fps, width, height)
        else:
            for i, rgb in enumerate(checked_frames()):
                pixels = rgb.astype(np.float32) / 255.0 if fmt == "exr" else rgb
                write_image(tmp / manifest["frame_files"].format(i), pixels)
        np.savez_compressed(tmp / TRACKING, **tracking.arrays())
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
        for p in (tmp, tmp / "masks", tmp / "frames"):
            if p.exists():
                os.chmod(p, 0o755)
        if out_dir.exists():
            out_dir.rmdir()  # empty (checked above); fails if something appeared meanwhile
        os.rename(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


# ---------------------------------------------------------------------------------------------------- commands
