#!/bin/sh
# `make docker-engine`: what the compose system test (tests/test_compose.py) needs, from Debian, where
# missing: the Docker engine (docker.io), compose (docker-compose: Debian has v1 only; a `docker compose`
# v2 plugin is used instead when present) and debootstrap (for the stand-in base image). Installs only as
# root with apt; elsewhere it says so and the test is skipped with the reason. Never starts anything:
# the test starts dockerd only if none answers, and stops it by its PID.
set -eu
need=""
command -v dockerd >/dev/null 2>&1 || docker info >/dev/null 2>&1 || need="$need docker.io"
docker compose version >/dev/null 2>&1 || command -v docker-compose >/dev/null 2>&1 || need="$need docker-compose"
command -v debootstrap >/dev/null 2>&1 || need="$need debootstrap"
[ -z "$need" ] && exit 0
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "docker-engine: not installing$need (needs root and apt): the compose system test will skip" >&2
    exit 0
fi
echo "docker-engine: installing$need from Debian"
log="${TMPDIR:-/tmp}/toptag-docker-engine-apt.log"
apt-get update -qq >"$log" 2>&1 || true  # a failing third-party list must not stop Debian's packages
# shellcheck disable=SC2086
if ! DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $need >>"$log" 2>&1; then
    tail -n 20 "$log" >&2
    exit 1
fi
