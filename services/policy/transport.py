"""gRPC settings shared by the robot's client, the policy server and its workers (grpc only: the
client imports this, and never torch).

Keepalive: a caller pings its connection every ``keepalive_s`` and closes it when a ping goes
unanswered as long, so that a peer that stopped answering with the socket still open -- a frozen
process, a host that died without closing, a NAT or firewall that forgot an idle connection -- is
left in seconds and the channel connects again (to the address's other servers, or to the same one
once back) instead of sending every call into it until TCP gives up (15 minutes on Linux). The
servers accept pings this often, idle or not (grpc's default would answer them with GOAWAY
``too_many_pings`` and drop the connection).
"""

from __future__ import annotations

# the most often a server accepts keepalive pings (callers ping every >= 1 s)
KEEPALIVE_MIN_PING_MS = 500


class ListenError(OSError):
    """A server cannot listen on the address it was given."""


# grpc servers set SO_REUSEPORT by default: a second server on a port another process holds would
# start without a word and the kernel would hand each new connection to either of them (a robot
# could get last week's policy). Every server here turns it off: the second one fails instead.
EXCLUSIVE_PORT = [("grpc.so_reuseport", 0)]


def bad_target(target: str) -> str | None:
    """Why ``target`` is not a gRPC address to connect to, or None. Targets: host:port, [v6]:port,
    dns:///name:port (or dns:name:port, dns://authority/name:port), ipv4:A:P,B:P, ipv6:[A]:P,...,
    and, not looked into, unix:path, unix-abstract:name, vsock:cid:port and xds:///name.
    gRPC takes what these checks refuse without a word, and then fails on every call: a URL
    (http://host:port), a port that is no number or missing (host alone: port 443) or out of range
    (99999 is taken modulo 65536: 34463), a typo'd separator; a server given such a worker waited
    for it its whole worker_ready_s."""
    if target.startswith(("unix:", "unix-abstract:", "vsock:")):
        return None if target.partition(":")[2] else f"nothing after {target}"
    if any(c.isspace() for c in target):
        return "has a space in it"
    rest = target
    if "://" in target:
        scheme, _, rest = target.partition("://")
        if scheme == "xds":  # (a service mesh's name, resolved by its control plane)
            return None
        if scheme != "dns":
            return f"{scheme}:// is not a gRPC address: give host:port (e.g. {rest.rstrip('/')})"
        rest = rest.partition("/")[2]  # (dns://authority/name:port: the authority is the DNS server)
    elif target.startswith(("ipv4:", "ipv6:", "dns:")):
        rest = target.partition(":")[2]
    for part in rest.split(","):
        if why := _bad_host_port(part):
            return why
    return None


def _bad_host_port(part: str) -> str | None:
    host, colon, port = part.rpartition(":")
    if not colon:
        return f"{part or '(nothing)'} has no port (gRPC would use 443): give host:port"
    if not port:
        return "nothing after the last ':': give host:port"
    if not port.isdigit():
        return f"port {port!r} is not a number"
    if not 0 < int(port) <= 65535:
        return f"port {port} is beyond 65535" if int(port) > 65535 else f"port {port} is no port to connect to"
    if not host:
        return f"no host before :{port}"
    if ":" in host and not (host.startswith("[") and host.endswith("]")):
        return f"host {host!r} has a ':' in it (an IPv6 address goes in brackets: [::1]:{port})"
    return None


def listen_on(server, address: str, credentials=None) -> int:
    """Bind a grpc (or grpc.aio) server made with EXCLUSIVE_PORT to ``address``; its port (port 0:
    any free one). ListenError naming the address and the reason when it cannot: found with a plain
    socket first, so that grpc's own error line ("add_port.cc ... Failed to add port") is not
    printed before ours for the usual reasons (a port taken, a host that does not resolve)."""
    if why := bind_problem(address):
        raise ListenError(f"cannot listen on {address}: {why}")
    try:
        return server.add_secure_port(address, credentials) if credentials else server.add_insecure_port(address)
    except RuntimeError:  # grpc says only "Failed to bind to address ..."
        why = bind_problem(address) or "grpc could not bind it (GRPC_VERBOSITY=debug says why)"
        raise ListenError(f"cannot listen on {address}: {why}") from None


def _resolve(address: str) -> tuple[str, list, str | None]:
    """(host, getaddrinfo's answers for host:port, why not: None when it resolves)."""
    import socket

    host, _, port = address.rpartition(":")
    host = host.strip("[]")
    try:
        return host, socket.getaddrinfo(host or None, int(port), type=socket.SOCK_STREAM), None
    except ValueError:
        return host, [], "not host:port (e.g. 127.0.0.1:50051, or 0.0.0.0:7001 for every interface)"
    except socket.gaierror:
        return host, [], f"{host!r} is not a name or address this machine resolves"


def unlistenable(address: str) -> str | None:
    """Why host:port can never be listened on here, whatever else runs, or None: not host:port, or
    a host this machine does not resolve. (A bad --listen, checked before anything starts.)"""
    return _resolve(address)[2]


def bind_problem(address: str) -> str | None:
    """Why a bind to host:port fails, found by trying it with a plain socket; None if it binds."""
    import errno
    import socket

    host, infos, why = _resolve(address)
    if why:
        return why
    for family, kind, proto, _, sockaddr in infos:
        with socket.socket(family, kind, proto) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind(sockaddr)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    return "another process holds the port"
                if exc.errno == errno.EADDRNOTAVAIL:
                    return f"{host} is not an address of this machine (0.0.0.0 listens on every interface)"
                return exc.strerror or str(exc)
    return None


def message_size_options(max_mb: int) -> list[tuple[str, int]]:
    """Channel or server options: messages of at most ``max_mb`` MiB, both ways."""
    size = max_mb << 20
    return [("grpc.max_receive_message_length", size), ("grpc.max_send_message_length", size)]


def keepalive_channel_options(keepalive_s: float) -> list[tuple[str, int]]:
    """Channel options: ping every ``keepalive_s``, idle or not; close the connection when a ping
    is unanswered for as long. Empty for 0 (no pings)."""
    if keepalive_s <= 0:
        return []
    ms = int(keepalive_s * 1e3)
    return [
        ("grpc.keepalive_time_ms", ms),
        ("grpc.keepalive_timeout_ms", ms),
        ("grpc.http2.ping_timeout_ms", ms),  # what closes the connection in grpc 1.85
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.max_pings_without_data", 0),
    ]


def keepalive_server_options() -> list[tuple[str, int]]:
    """Server options: accept the callers' pings (every >= KEEPALIVE_MIN_PING_MS), idle or not."""
    return [
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.min_ping_interval_without_data_ms", KEEPALIVE_MIN_PING_MS),
    ]
