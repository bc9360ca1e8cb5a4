"""A real RTSP server on loopback for the camera tests: GStreamer's gst-rtsp-server streaming
numbered frames as RTP/JPEG, the way an IP camera serves its stream to a pulling client.

Run by the system Python (``/usr/bin/python3``, which has PyGObject; Debian packages installed by
``deploy/install-system-deps.sh``)::

    /usr/bin/python3 tests/integration/rtsp_server.py --port 0 --fps 20 --start 0

It prints ``ready rtsp://127.0.0.1:<port>/cam`` once it listens (port 0: the OS picks one) and
serves until killed. Each frame carries its number in ``BITS`` black/white vertical bars
(``frame_bytes``; the tests decode them with ``code_of``), so a client can check order, repeats
and what a gap skipped. Pure Python here: the system interpreter has no numpy.
"""

from __future__ import annotations

import argparse
import sys

BITS = 10  # bars per frame: frame numbers modulo 1024


def frame_bytes(n: int, width: int, height: int) -> bytes:
    """(height, width, 3) uint8 RGB, row-major: bar k (from the left) is white iff bit k of n is set."""
    row = bytearray()
    for x in range(width):
        bit = min(x * BITS // width, BITS - 1)
        row += b"\xff\xff\xff" if (n >> bit) & 1 else b"\x00\x00\x00"
    return bytes(row) * height


def code_of(rgb) -> int:
    """The frame number in an (H, W, 3) RGB array (numpy, any size): the inverse of ``frame_bytes``."""
    height, width = rgb.shape[:2]
    row = rgb[height // 2].mean(axis=1)  # (W,)
    n = 0
    for bit in range(BITS):
        x = int((bit + 0.5) * width / BITS)
        n |= int(row[x] > 127) << bit
    return n


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, default=0, help="0: any free port")
    parser.add_argument("--fps", type=int, default=20)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--start", type=int, default=0, help="number of the first frame served")
    args = parser.parse_args()

    import gi

    gi.require_version("Gst", "1.0")
    gi.require_version("GstRtspServer", "1.0")
    from gi.repository import GLib, Gst, GstRtspServer

    Gst.init(None)
    counter = [args.start]
    duration = Gst.SECOND // args.fps

    def on_configure(_factory, media):
        src = media.get_element().get_child_by_name("src")
        pts = [0]

        def need_data(appsrc, _length):
            # gst-rtsp-server's test-appsrc pattern: buffers carry their presentation time and the
            # media pipeline's sinks pace them against the clock, so frames go out at --fps.
            buf = Gst.Buffer.new_wrapped(frame_bytes(counter[0], args.width, args.height))
            buf.pts = pts[0]
            buf.duration = duration
            pts[0] += duration
            counter[0] += 1
            appsrc.emit("push-buffer", buf)

        src.connect("need-data", need_data)

    caps = f"video/x-raw,format=RGB,width={args.width},height={args.height},framerate={args.fps}/1"
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(
        f"( appsrc name=src format=time caps={caps} ! videoconvert ! video/x-raw,format=I420 ! "
        "jpegenc quality=95 ! rtpjpegpay name=pay0 pt=26 )"
    )
    factory.connect("media-configure", on_configure)
    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(args.port))
    server.get_mount_points().add_factory("/cam", factory)
    if server.attach(None) == 0:
        print(f"error: cannot listen on 127.0.0.1:{args.port}", file=sys.stderr, flush=True)
        return 1
    print(f"ready rtsp://127.0.0.1:{server.get_bound_port()}/cam", flush=True)
    GLib.MainLoop().run()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
