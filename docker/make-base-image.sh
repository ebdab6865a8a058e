#!/usr/bin/env bash
# Make a local Debian base image for docker/Dockerfile when no image registry is
# reachable (python:3.11-slim cannot be pulled): debootstrap a minimal bookworm (its
# python3 is 3.11) from Debian's package mirror and `docker import` it.
#
#   docker/make-base-image.sh [IMAGE]        # default IMAGE: skyloop-base:bookworm
#   docker build --build-arg BASE=skyloop-base:bookworm ...
#
# Cached: does nothing when IMAGE already exists (delete it with `docker rmi IMAGE` to
# make it again). Needs root, debootstrap and a running Docker engine; about a minute.
# The host's CA bundle and its pip settings that matter (the CA file) are copied in, so
# pip inside `docker build --network host` trusts the same registries as the host.
set -euo pipefail

IMAGE=${1:-skyloop-base:bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
SUITE=${DEBIAN_SUITE:-bookworm}

if docker image inspect "$IMAGE" >/dev/null 2>&1; then
    echo "make-base-image: $IMAGE exists (cached)"
    exit 0
fi
command -v debootstrap >/dev/null || {
    echo "make-base-image: debootstrap missing (apt-get install debootstrap)" >&2; exit 1; }

ROOTFS=$(mktemp -d /tmp/skyloop-rootfs.XXXXXX)
trap 'rm -rf "$ROOTFS"' EXIT
echo "make-base-image: debootstrap $SUITE into $ROOTFS"
# python3-venv: the Dockerfile makes a venv (Debian's python3 is externally managed);
# libgomp1: OpenMP for numba and others.
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates,libgomp1 \
    "$SUITE" "$ROOTFS" "$MIRROR" >/tmp/skyloop-debootstrap.log 2>&1 || {
    tail -20 /tmp/skyloop-debootstrap.log >&2; exit 1; }

# Trust what the host trusts (a TLS-inspecting proxy's CA, if any), for pip as well.
if [ -f /etc/ssl/certs/ca-certificates.crt ]; then
    cp /etc/ssl/certs/ca-certificates.crt "$ROOTFS/etc/ssl/certs/ca-certificates.crt"
fi
printf '[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n' > "$ROOTFS/etc/pip.conf"
# Slim it: apt lists, caches, docs and locales are not needed at run time.
chroot "$ROOTFS" apt-get clean
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/* \
       "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/* \
       "$ROOTFS"/usr/share/locale/*

tar -C "$ROOTFS" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' - "$IMAGE" >/dev/null
echo "make-base-image: $IMAGE ($(docker image inspect -f '{{.Size}}' "$IMAGE" |
    awk '{printf "%.0f MB", $1/1e6}'))"
