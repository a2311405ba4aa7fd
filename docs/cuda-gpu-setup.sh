#!/usr/bin/env bash
# Set this checkout up on a GPU machine without network access (docs/cuda-gpu-runbook.md): install the carried
# wheels, build and install the package (native extension and gRPC stubs), put the carried open head where the
# commands look for it, and build gsplat's CUDA extension (minutes, once per machine). Idempotent.
# Usage, from the repository root: bash docs/cuda-gpu-setup.sh [CARRY_DIR (default gpu-carry)]
set -euo pipefail
carry="${1:-gpu-carry}"
py="${PYTHON:-python3}"
if ! "$py" -c "import gsplat, OpenImageIO, grpc_tools" 2>/dev/null; then
    "$py" -m pip install -q --no-index --no-deps "$carry"/wheels/*.whl
fi
if ! "$py" -c "import render_core._native" 2>/dev/null; then
    "$py" -m pip install -q --no-build-isolation --no-deps -e .
fi
if [ -f "$carry/open-head.facemodel" ] && [ ! -f data/facemodels/open-head.facemodel ]; then
    mkdir -p data/facemodels && cp "$carry/open-head.facemodel" data/facemodels/
fi
# A gsplat build carried from an earlier machine (docs/cuda-gpu-check.sh packs it as gsplat-ext.tar.gz.*): restored
# and made newer than the sources the wheel just installed, so ninja relinks nothing (77 s saved on an H100).
ext="$HOME/.cache/torch_extensions"
if ls "$carry"/gsplat-ext.tar.gz.* >/dev/null 2>&1 && [ ! -d "$ext" ]; then
    mkdir -p "$ext" && cat "$carry"/gsplat-ext.tar.gz.* | tar xzf - -C "$ext" && find "$ext" -exec touch {} +
fi
export TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST:-9.0}" MAX_JOBS="${MAX_JOBS:-16}"
"$py" - <<'PY'
import time

import gsplat
import torch

print(f"torch {torch.__version__} (CUDA {torch.version.cuda}) on {torch.cuda.get_device_name()}, gsplat {gsplat.__version__}")
from render_core.raster import gsplat_backend  # noqa: E402

t = time.perf_counter()
gsplat_backend.build_extension()
print(f"gsplat's CUDA extension ready after {time.perf_counter() - t:.0f} s; backends:",
      __import__("render_core.raster", fromlist=["backend_names"]).backend_names())
PY
