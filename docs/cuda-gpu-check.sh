#!/usr/bin/env bash
# One device call that proves the cuda path (docs/cuda-gpu-runbook.md): set up (or reuse a carried gsplat build),
# pack the built extension for the next call, run the GPU tests, the render / raster-backward benchmarks with a
# torch.profiler trace, and a short training run on each device. Every result is written under OUT as soon as it
# exists, so a run cut short still returns what it finished.
# Usage, from the repository root: OUT=dir bash docs/cuda-gpu-check.sh [CARRY_DIR (default gpu-carry)] [STEPS]
#   STEPS: a space-separated subset of "setup tests bench train" (default: all).
#   FUSES (environment): the render cases' fuse modes, default "graph off compile" ("off" runs the sparse layout).
set -uo pipefail
carry="${1:-gpu-carry}"
steps="${2:-setup tests bench train}"
OUT="${OUT:?OUT must name the folder results go to}"
out=/tmp/gpu-results  # everything small, packed into $OUT/results.tgz after each step (the tool returns 8 files)
mkdir -p "$out"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST:-9.0}" MAX_JOBS="${MAX_JOBS:-16}"
ext="$HOME/.cache/torch_extensions"
py=python3
log() { echo "[$(date +%T)] $*" | tee -a "$out/steps.txt"; tar czf "$OUT/results.tgz" -C "$out" .; }
has() { [[ " $steps " == *" $1 "* ]]; }

nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader > "$out/gpu.txt" 2>&1
if has setup; then
    log "setup"
    bash docs/cuda-gpu-setup.sh "$carry" > "$out/setup.txt" 2>&1 || { log "setup failed"; tail -60 "$out/setup.txt"; exit 1; }
    tail -3 "$out/setup.txt"
    if ! ls "$carry"/gsplat-ext.tar.gz* >/dev/null 2>&1; then
        tar czf - -C "$ext" . | split -b 15M - "$OUT/gsplat-ext.tar.gz."
        log "packed the gsplat build: $(du -ch "$OUT"/gsplat-ext.tar.gz.* | tail -1)"
    fi
fi
if has tests; then
    log "cuda tests"
    timeout 240 $py -m pytest -m cuda -rs -s -q -p no:cacheprovider tests/test_cuda.py > "$out/pytest-cuda.txt" 2>&1
    log "cuda tests exit $?: $(tail -1 "$out/pytest-cuda.txt")"
fi
B="$py -m render_core.tools.cli bench"
A="--backend cuda --size 512 --reference-frames 0 --json"
if has bench; then
    [ -f /tmp/open-head.bsplat ] || $py -m render_core.tools.cli bundle init --out /tmp/open-head.bsplat \
        --gaussians 60000 --mouth 4000 --opacity 0.95 --albedo demo > /dev/null 2>&1
    run() { local name=$1; shift; log "bench $name"; timeout 120 "$@" > "$out/$name.json" 2> "$out/$name.err" \
        || log "bench $name failed: $(tail -2 "$out/$name.err")"; }
    D="--gaussians 64000 --blendshapes 50"; O="--bundle /tmp/open-head.bsplat"
    # before (eager stages over the stored pairs) and after (dense matrix, one CUDA graph; torch.compile's kernels)
    for fuse in ${FUSES:-graph off compile}; do
        L=$([ $fuse = off ] && echo sparse || echo dense)
        [ $fuse = graph ] && T="--trace /tmp/trace-dense-1.json" || T=""
        run render-dense-1-$fuse $B render $A $D --fuse $fuse --layout $L --frames 300 --warmup 30 $T
        run render-dense-32-$fuse $B render $A $D --fuse $fuse --layout $L --streams 32 --frames 50 --warmup 5
        [ $fuse = compile ] && continue
        run render-openhead-1-$fuse $B render $A $O --fuse $fuse --layout $L --frames 300 --warmup 30
        run render-openhead-32-$fuse $B render $A $O --fuse $fuse --layout $L --streams 32 --frames 50 --warmup 5
    done
    run render-dense-1-bf16 $B render $A $D --precision bf16 --frames 300 --warmup 30
    run raster-backward $B raster-backward --device cuda --gaussians 64000 --size 512 --frames 50 --reference-frames 3 --json
    for t in /tmp/trace-*.json; do gzip -c "$t" > "$OUT/$(basename "$t").gz"; done
fi
if has train; then
    log "train"
    $py -m render_core.tools.cli data synth --out /tmp/ds --frames 120 --size 256 --seed 7 > /dev/null 2>&1
    for d in cuda cpu; do
        timeout 150 $py -m render_core.tools.cli train /tmp/ds --out /tmp/$d.bsplat --workdir /tmp/$d.train --preset tiny \
            --device $d --iterations 200 --quiet > "$out/train-$d.json" 2> "$out/train-$d.err" || log "train $d failed: $(tail -2 "$out/train-$d.err")"
    done
fi
$py - "$out" <<'PY'
import json, pathlib, sys
keys = ("fps", "aggregate_fps", "ms", "precision", "fuse", "fuse_error", "ms_per_iteration", "stage_ms")
for p in sorted(pathlib.Path(sys.argv[1]).glob("*.json")):
    try:
        r = json.loads(p.read_text())
    except ValueError:
        continue
    print(p.stem, json.dumps({k: r[k] for k in keys if r.get(k) is not None}))
    for row in (r.get("profile") or {}).get("top", [])[:8]:
        print("   ", row)
PY
log "done"
