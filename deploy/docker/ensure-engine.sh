#!/usr/bin/env bash
# Make a Docker engine answer on this machine: install Debian's docker.io if dockerd is missing,
# start dockerd if it is not running, wait until it answers. Idempotent; an engine that already
# answers (Docker Desktop, a systemd-managed dockerd) is left exactly as it is.
#
#   deploy/docker/ensure-engine.sh          # exit 0: `docker info` works
#
# A dockerd started here touches nothing outside itself: no host firewall rules (--iptables=false),
# no IP forwarding, no default bridge. Containers reach each other on compose's internal network;
# image builds use the host network (compose's build.network: host). Storage: overlay2, or vfs
# where the filesystem cannot host overlay2. Log: $DOCKERD_LOG.
set -euo pipefail

DOCKERD_LOG="${DOCKERD_LOG:-/var/log/viewscale-dockerd.log}"
WAIT_S="${DOCKERD_WAIT_S:-60}"

log() { echo "[ensure-engine] $*"; }
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"

engine_up() { docker info >/dev/null 2>&1; }

wait_engine() {  # $1: pid of the dockerd we started (empty: started by systemd)
  local i
  for ((i = 0; i < WAIT_S * 2; i++)); do
    engine_up && return 0
    if [ -n "${1:-}" ] && ! kill -0 "$1" 2>/dev/null; then return 1; fi
    sleep 0.5
  done
  return 1
}

if command -v docker >/dev/null 2>&1 && engine_up; then
  log "engine already running: $(docker version --format 'server {{.Server.Version}}, client {{.Client.Version}}')"
  exit 0
fi

if command -v docker >/dev/null 2>&1 && [[ "$(docker info 2>&1 || true)" == *"permission denied"* ]]; then
  log "an engine runs but $(id -un) may not use its socket: join the docker group or run as root"
  exit 1
fi

start=$(date +%s)
if ! command -v dockerd >/dev/null 2>&1 && [ ! -x /usr/sbin/dockerd ]; then
  log "dockerd missing: installing Debian's docker.io"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends docker.io
  log "installed docker.io in $(( $(date +%s) - start )) s"
fi
PATH="$PATH:/usr/sbin:/sbin"

if [ -d /run/systemd/system ] && command -v systemctl >/dev/null 2>&1; then
  log "starting docker.service (systemd)"
  $SUDO systemctl start docker
  wait_engine "" || { log "docker.service did not answer in ${WAIT_S} s"; $SUDO systemctl status docker --no-pager || true; exit 1; }
else
  # No init system to ask: run dockerd ourselves, detached from this shell.
  if pgrep -x dockerd >/dev/null 2>&1; then
    log "dockerd is running but does not answer yet; waiting"
    wait_engine "" || { log "dockerd (pid $(pgrep -x dockerd)) did not answer in ${WAIT_S} s"; exit 1; }
  else
    flags=(--iptables=false --ip-forward=false --ip-masq=false --bridge=none)
    for driver in overlay2 vfs; do
      log "starting dockerd --storage-driver=$driver ${flags[*]} (log: $DOCKERD_LOG)"
      $SUDO sh -c "setsid dockerd --storage-driver=$driver ${flags[*]} >>'$DOCKERD_LOG' 2>&1 </dev/null & echo \$! >/run/viewscale-dockerd.pid"
      pid=$($SUDO cat /run/viewscale-dockerd.pid)
      if wait_engine "$pid"; then break; fi
      log "dockerd with $driver did not come up; last log lines:"
      $SUDO tail -n 15 "$DOCKERD_LOG" || true
      $SUDO kill "$pid" 2>/dev/null || true
      for _ in $(seq 20); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
      [ "$driver" = vfs ] && { log "no storage driver worked"; exit 1; }
    done
  fi
fi
log "engine up in $(( $(date +%s) - start )) s: $(docker info --format 'server {{.ServerVersion}}, storage {{.Driver}}, cgroup {{.CgroupVersion}}')"
