# Blendsplat images: two targets, both run `blendsplat serve` by default (`worker`, `up`, `migrate` as commands).
#
#   cpu   the native CPU renderer (C++ extension built in a builder stage), torch's CPU build
#   cuda  torch with CUDA and gsplat's kernels compiled at build time for TORCH_CUDA_ARCH_LIST
#
#   docker build --target cpu  -t REGISTRY/blendsplat:TAG-cpu .
#   docker build --target cuda -t REGISTRY/blendsplat:TAG-cuda .
#
# The final stages hold Python, the virtual environment and the runtime libraries: no compiler, no pip cache, no
# build context. A non-root user (uid 10001) owns /data (BLENDSPLAT_DATA_DIR). The servers listen on every interface
# (BLENDSPLAT_HOST=0.0.0.0: outside a container the default is 127.0.0.1). The entry point is the exec form,
# so SIGTERM reaches the service itself (it drains; a worker checkpoints). Build with `--format docker` under
# podman/buildah: the OCI format has no HEALTHCHECK. deploy/smoke builds and runs the cpu target on a local base.

# Public bases by default; deploy/smoke passes a local Debian bookworm root as BASE_IMAGE.
ARG BASE_IMAGE=docker.io/library/debian:bookworm-slim
ARG CUDA_DEVEL_IMAGE=docker.io/nvidia/cuda:13.0.1-devel-ubuntu24.04
ARG CUDA_RUNTIME_IMAGE=docker.io/nvidia/cuda:13.0.1-runtime-ubuntu24.04

# ----------------------------------------------------------------------------------------------- cpu: build
# Few instructions after the large layers: podman's vfs storage (deploy/smoke) copies a whole layer per step.
FROM ${BASE_IMAGE} AS cpu-builder
SHELL ["/bin/bash", "-o", "pipefail", "-c"]
# torch's CPU build: from the wheels in deploy/wheels/ when there are any (the build context; deploy/smoke puts
# the local file there), else from PyTorch's CPU index (PyPI's Linux torch is the CUDA build).
ARG TORCH_VERSION=2.13.0+cpu
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV DEBIAN_FRONTEND=noninteractive \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_CERT=/etc/ssl/certs/ca-certificates.crt \
    PATH=/opt/blendsplat/venv/bin:$PATH
# Debian's own packages, pinned by the base image's release (bookworm).
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates python3 python3-venv python3-dev g++ make cmake \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /opt/blendsplat/venv
RUN --mount=type=bind,source=deploy/wheels,target=/tmp/wheels \
    pip install --find-links /tmp/wheels --extra-index-url "${TORCH_INDEX_URL}" "torch==${TORCH_VERSION}"
# The project's dependencies (with the `train` extra: the jobs' figures) and build requirements: layers that
# survive source changes (a COPY, not a bind mount: buildah's cache key ignores a bind mount's contents). The Python
# client package (clients/python, a dependency that is not on PyPI) is installed first.
COPY clients/python /tmp/clients-python
COPY pyproject.toml /tmp/pyproject.toml
RUN pip install /tmp/clients-python \
    && python3 -c 'import tomllib; p = tomllib.load(open("/tmp/pyproject.toml", "rb")); print("\n".join(p["project"]["dependencies"] + p["project"]["optional-dependencies"]["train"] + p["build-system"]["requires"]))' > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt
# The sources (.dockerignore keeps only the package, its build files and deploy/'s image files), built and checked.
COPY . /src/
RUN pip install --no-build-isolation --no-deps /src \
    && pip uninstall -y scikit-build-core nanobind grpcio-tools \
    && install -m 0644 /src/deploy/healthcheck.py /opt/blendsplat/healthcheck.py \
    && rm -rf /opt/blendsplat/venv/lib/python3*/site-packages/torch/include \
    && python3 -P -c 'import render_core._native, blendsplat.v1.render_pb2_grpc, blendsplat_client, service.cli'

# ----------------------------------------------------------------------------------------------- cpu: final
FROM ${BASE_IMAGE} AS cpu
ENV PATH=/opt/blendsplat/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    BLENDSPLAT_DATA_DIR=/data \
    BLENDSPLAT_HOST=0.0.0.0
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 libgomp1 \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --uid 10001 --user-group --create-home --home-dir /home/blendsplat --shell /usr/sbin/nologin \
       blendsplat \
    && install -d -o 10001 -g 10001 /data
USER 10001:10001
WORKDIR /home/blendsplat
EXPOSE 50051 8080
HEALTHCHECK --interval=15s --timeout=5s --start-period=120s --retries=3 \
    CMD ["python3", "/opt/blendsplat/healthcheck.py"]
ENTRYPOINT ["blendsplat"]
CMD ["serve"]
# Last: the one large layer of the final image (the virtual environment and the health check script).
COPY --from=cpu-builder /opt/blendsplat /opt/blendsplat

# ---------------------------------------------------------------------------------------------- cuda: build
# Ubuntu 24.04's Python 3.12, torch with CUDA from PyTorch's index, gsplat's CUDA kernels compiled here, once, for
# TORCH_CUDA_ARCH_LIST (no nvcc at run time, no JIT build on the first frame).
FROM ${CUDA_DEVEL_IMAGE} AS cuda-builder
SHELL ["/bin/bash", "-o", "pipefail", "-c"]
ARG TORCH_CUDA_VERSION=2.11.0
ARG TORCH_CUDA_INDEX_URL=https://download.pytorch.org/whl/cu130
ARG TORCH_CUDA_ARCH_LIST="8.0;8.6;8.9;9.0;10.0;12.0"
ARG MAX_JOBS=8
ENV DEBIAN_FRONTEND=noninteractive \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PIP_CERT=/etc/ssl/certs/ca-certificates.crt \
    TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST} \
    MAX_JOBS=${MAX_JOBS} \
    PATH=/opt/blendsplat/venv/bin:$PATH
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends ca-certificates python3 python3-venv python3-dev g++ make cmake \
       ninja-build \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /opt/blendsplat/venv
RUN pip install --extra-index-url "${TORCH_CUDA_INDEX_URL}" "torch==${TORCH_CUDA_VERSION}" \
       "setuptools>=70" "wheel>=0.43" "ninja>=1.11" \
    && pip install --no-build-isolation --no-binary gsplat "gsplat==1.5.3" \
    && python3 -P -c 'from gsplat import csrc'
COPY clients/python /tmp/clients-python
COPY pyproject.toml /tmp/pyproject.toml
RUN pip install /tmp/clients-python \
    && python3 -c 'import tomllib; p = tomllib.load(open("/tmp/pyproject.toml", "rb")); print("\n".join(p["project"]["dependencies"] + p["project"]["optional-dependencies"]["train"] + p["build-system"]["requires"]))' > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt
COPY . /src/
RUN pip install --no-build-isolation --no-deps /src \
    && pip uninstall -y scikit-build-core nanobind grpcio-tools ninja \
    && install -m 0644 /src/deploy/healthcheck.py /opt/blendsplat/healthcheck.py \
    && rm -rf /opt/blendsplat/venv/lib/python3*/site-packages/torch/include \
    && python3 -P -c 'import render_core._native, blendsplat.v1.render_pb2_grpc, blendsplat_client, service.cli'

# ---------------------------------------------------------------------------------------------- cuda: final
FROM ${CUDA_RUNTIME_IMAGE} AS cuda
ENV PATH=/opt/blendsplat/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    BLENDSPLAT_DATA_DIR=/data \
    BLENDSPLAT_HOST=0.0.0.0 \
    BLENDSPLAT_BACKEND=cuda \
    NVIDIA_VISIBLE_DEVICES=all \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 libgomp1 \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --uid 10001 --user-group --create-home --home-dir /home/blendsplat --shell /usr/sbin/nologin \
       blendsplat \
    && install -d -o 10001 -g 10001 /data
USER 10001:10001
WORKDIR /home/blendsplat
EXPOSE 50051 8080
HEALTHCHECK --interval=15s --timeout=5s --start-period=300s --retries=3 \
    CMD ["python3", "/opt/blendsplat/healthcheck.py"]
ENTRYPOINT ["blendsplat"]
CMD ["serve"]
COPY --from=cuda-builder /opt/blendsplat /opt/blendsplat
