#!/usr/bin/env bash
# System libraries for headless MuJoCo rendering (EGL, OSMesa fallback), and the RTSP server the
# camera tests stream from (GStreamer's gst-rtsp-server with its Python bindings for the system
# python3: appsrc, jpegenc, rtpjpegpay). Idempotent: installs only what is missing.
set -euo pipefail
need=()
for pkg in libegl1 libgl1-mesa-dri libosmesa6 \
    python3-gi gir1.2-gst-rtsp-server-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "installing system packages: ${need[*]}"
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q "${need[@]}"
fi
