#!/usr/bin/env bash
# The tracker's end-to-end measurement (the video-to-avatar issue's goal): an avatar trained on `blendsplat track`'s
# output of a synthetic H.264 video against one trained on the TRUE tracking and masks of the same decoded frames,
# both scored on the true frames and masks (held-out head PSNR, `eval --align 100 --align-expressions`).
#   docs/tracker-end-to-end.sh SEED [ITERATIONS] [WORKDIR]     (from the project root, after the README set-up)
# About 15 minutes on 2 cores at the defaults (150 frames at 256 px, tiny preset, 1500 iterations); prints one line.
set -euo pipefail
SEED=$1; IT=${2:-1500}; W=${3:-scratch/tracker-e2e/$SEED}
ROOT=$(pwd); BS="$ROOT/.venv/bin/blendsplat"; PY="$ROOT/.venv/bin/python"
mkdir -p "$W"; cd "$W"
[ -d truth ] || "$BS" data synth --out truth --frames 150 --size 256 --seed "$SEED" >/dev/null 2>&1
[ -f clip.mp4 ] || "$PY" - <<'PY'
from pathlib import Path
import numpy as np
from PIL import Image
from render_core.tracking.known_answer import encode_h264
frames = sorted(Path("truth/frames").glob("*.png"))
encode_h264((np.asarray(Image.open(p).convert("RGB")) for p in frames), "clip.mp4", fps=30, crf=20)
PY
rm -rf tracked; "$BS" track clip.mp4 --out tracked --size 256 --fps 30 --crop none --json >track.json 2>/dev/null
hybrid() {  # NAME TRACKING-FROM FRAMES-FROM MASKS-FROM (hard links: the format refuses links out of the folder)
  rm -rf "$1"; mkdir "$1"; cp truth/dataset.json "$1"/; cp -l "$2"/tracking.npz "$1"/
  cp -al "$3"/frames "$1"/frames; cp -al "$4"/masks "$1"/masks; }
hybrid reference truth tracked truth   # the true tracking and masks on the video's decoded frames
hybrid score-reference truth truth truth
hybrid score-tracked tracked truth truth
"$BS" train reference --out reference.bundle --preset tiny --iterations "$IT" >/dev/null 2>&1
"$BS" train tracked --out tracked.bundle --preset tiny --iterations "$IT" --refine-expressions >/dev/null 2>&1
for k in reference tracked; do
  "$BS" eval --bundle $k.bundle --data score-$k --align 100 --align-expressions --json >$k.eval.json 2>/dev/null
done
"$PY" - "$SEED" <<'PY'
import json, sys
r, t = (json.load(open(f"{k}.eval.json")) for k in ("reference", "tracked"))
print(json.dumps({"seed": int(sys.argv[1]), "reference_psnr_head": round(r["psnr_head"], 2),
                  "tracked_psnr_head": round(t["psnr_head"], 2), "gap_db": round(r["psnr_head"] - t["psnr_head"], 2),
                  "tracked_unaligned": round(t["unaligned"]["psnr_head"], 2)}))
PY
