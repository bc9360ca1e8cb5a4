#!/usr/bin/env bash
# Make `docker compose` (v2) available. Idempotent: nothing happens when it already is.
#
#   deploy/docker/ensure-compose.sh
#
# Compose v2 is built from its Go module (the Go module proxy is reachable where no GitHub
# release or image registry is) and installed as a Docker CLI plugin. Debian bookworm ships only
# compose v1, which lacks build secrets and BuildKit builds that docker-compose.yml relies on.
# Go's module and build caches make a rebuild after the plugin is lost take seconds.
set -euo pipefail

COMPOSE_VERSION="${COMPOSE_VERSION:-v2.29.7}"
log() { echo "[ensure-compose] $*"; }

current=$(docker compose version --short 2>/dev/null || true)
case "$current" in
  2.*|v2.*)
    log "docker compose $current already available"
    exit 0 ;;
esac

if [ "$(id -u)" -eq 0 ]; then
  PLUGIN_DIR=/usr/local/lib/docker/cli-plugins  # searched by every docker CLI, for every user
else
  PLUGIN_DIR="${DOCKER_CONFIG:-$HOME/.docker}/cli-plugins"
fi

if ! command -v go >/dev/null 2>&1; then
  log "go is not installed: install Go >= 1.21 (or Docker's compose plugin) and run this again"
  exit 1
fi

start=$(date +%s)
build_dir=$(mktemp -d)
trap 'rm -rf "$build_dir"' EXIT
log "building docker compose $COMPOSE_VERSION with $(go version | cut -d' ' -f3) (first time: about 3 min)"
GOBIN="$build_dir" GOFLAGS="${GOFLAGS:-} -buildvcs=false" CGO_ENABLED=0 go install \
  -ldflags "-s -w -X github.com/docker/compose/v2/internal.Version=$COMPOSE_VERSION" \
  "github.com/docker/compose/v2/cmd@$COMPOSE_VERSION"
mkdir -p "$PLUGIN_DIR"
install -m 0755 "$build_dir/cmd" "$PLUGIN_DIR/docker-compose"
log "installed $PLUGIN_DIR/docker-compose in $(( $(date +%s) - start )) s: $(docker compose version)"
