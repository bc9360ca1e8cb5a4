#!/usr/bin/env bash
# Build the local base image viewscale-base:bookworm (a minimal Debian bookworm root filesystem,
# made with debootstrap and `docker import`ed) for machines that reach Debian's package mirror
# but no image registry. Idempotent: does nothing when the image is already there.
#
#   deploy/docker/build-base-image.sh            # builds viewscale-base:bookworm if missing
#   FORCE=1 deploy/docker/build-base-image.sh    # rebuilds it
#
# The mirror is the one this machine's apt sources use for bookworm (override: DEBIAN_MIRROR).
set -euo pipefail

IMAGE="${BASE_IMAGE_TAG:-viewscale-base:bookworm}"
SUITE=bookworm

log() { echo "[build-base-image] $*"; }

if [ "${FORCE:-0}" != 1 ] && docker image inspect "$IMAGE" >/dev/null 2>&1; then
  log "$IMAGE already present ($(docker image inspect -f '{{.Size}}' "$IMAGE") bytes); nothing to do"
  exit 0
fi

SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"

# First Debian archive URI that apt uses for the plain suite (not -security/-updates), from
# one-line .list files or deb822 .sources stanzas.
apt_mirror() {
  local f
  for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
    [ -r "$f" ] || continue
    awk -v s="$SUITE" '$1 == "deb" {
        i = 2; if ($2 ~ /^\[/) { while (i <= NF && $i !~ /\]$/) i++; i++ }
        if ($(i+1) == s) { print $i; exit } }' "$f"
  done
  for f in /etc/apt/sources.list.d/*.sources; do
    [ -r "$f" ] || continue
    awk -v s="$SUITE" '
      function flush() { if (uris != "" && (" " suites " ") ~ (" " s " ") && types ~ /(^| )deb( |$)/) { split(uris, u, " "); print u[1]; found = 1 } uris = suites = types = "" }
      /^[[:space:]]*$/ { flush(); if (found) exit; next }
      /^URIs:/   { sub(/^URIs:[[:space:]]*/, "");   uris = $0 }
      /^Suites:/ { sub(/^Suites:[[:space:]]*/, ""); suites = $0 }
      /^Types:/  { sub(/^Types:[[:space:]]*/, "");  types = $0 }
      END { if (!found) flush() }' "$f"
  done
}

MIRROR="${DEBIAN_MIRROR:-$(apt_mirror | head -n1)}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"
log "building $IMAGE from $SUITE at $MIRROR"

if ! command -v debootstrap >/dev/null 2>&1; then
  log "installing debootstrap"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends debootstrap
fi

ROOTFS="$(mktemp -d /var/tmp/viewscale-rootfs.XXXXXX)"
trap '$SUDO rm -rf "$ROOTFS"' EXIT

start=$(date +%s)
log "debootstrap --variant=minbase $SUITE -> $ROOTFS"
$SUDO debootstrap --variant=minbase "$SUITE" "$ROOTFS" "$MIRROR" >"$ROOTFS.log" 2>&1 || {
  tail -n 30 "$ROOTFS.log"; rm -f "$ROOTFS.log"; exit 1; }
rm -f "$ROOTFS.log"

# A smaller, reproducible-enough image: no package caches, lists or docs.
$SUDO chroot "$ROOTFS" apt-get clean
$SUDO rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/var/log/*.log \
  "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/*
# Image builds run apt-get non-interactively and want no recommended extras.
printf 'APT::Install-Recommends "false";\nAPT::Install-Suggests "false";\n' \
  | $SUDO tee "$ROOTFS/etc/apt/apt.conf.d/90viewscale-minimal" >/dev/null

log "docker import -> $IMAGE"
$SUDO tar -C "$ROOTFS" --numeric-owner -c . | docker import \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' \
  --change 'CMD ["bash"]' \
  --message "debootstrap --variant=minbase $SUITE $MIRROR" - "$IMAGE" >/dev/null
log "done in $(( $(date +%s) - start )) s: $IMAGE, $(docker image inspect -f '{{.Size}}' "$IMAGE") bytes"
