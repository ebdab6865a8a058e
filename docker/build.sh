#!/usr/bin/env bash
# Build the skyloop image (docker/Dockerfile) and report its size.
#
#   docker/build.sh [IMAGE]          # default IMAGE: skyloop:latest
#
# Base image: $SKYLOOP_BASE if set; else python:3.11-slim when it is present or can be
# pulled; else (no registry reachable) a Debian bookworm base made with debootstrap by
# docker/make-base-image.sh (cached: made once).
# Torch: a CPU wheel (torch-*+cpu-*.whl) found in $SKYLOOP_TORCH_WHEELS (default
# /opt/wheels) is installed from the build context (docker/wheels/, never committed);
# else PyTorch's CPU index ($SKYLOOP_TORCH_SOURCE overrides either).
# pip runs inside `docker build --network host`, so it reaches what the host reaches.
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE=${1:-skyloop:latest}

base=${SKYLOOP_BASE:-}
if [ -z "$base" ]; then
    if docker image inspect python:3.11-slim >/dev/null 2>&1 ||
       timeout 120 docker pull -q python:3.11-slim >/dev/null 2>&1; then
        base=python:3.11-slim
    else
        echo "build: python:3.11-slim cannot be pulled; using a local Debian base"
        docker/make-base-image.sh skyloop-base:bookworm
        base=skyloop-base:bookworm
    fi
fi

source=${SKYLOOP_TORCH_SOURCE:-}
if [ -z "$source" ]; then
    source=https://download.pytorch.org/whl/cpu
    wheel=$(ls "${SKYLOOP_TORCH_WHEELS:-/opt/wheels}"/torch-*+cpu-cp311-*.whl 2>/dev/null |
            sort | tail -n1 || true)
    if [ -n "$wheel" ]; then
        rm -f docker/wheels/torch-*.whl
        ln "$wheel" docker/wheels/ 2>/dev/null || cp "$wheel" docker/wheels/
        source=wheels
    fi
fi

echo "build: $IMAGE from $base, torch from $source"
start=$(date +%s)
docker build --network host -f docker/Dockerfile -t "$IMAGE" \
    --build-arg BASE="$base" --build-arg TORCH_SOURCE="$source" .
size=$(docker image inspect -f '{{.Size}}' "$IMAGE")
echo "build: $IMAGE built in $(( $(date +%s) - start )) s, size $(awk -v s="$size" \
    'BEGIN {printf "%.2f GB (%d MB)", s/1e9, s/1e6}')"
