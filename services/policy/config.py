"""Settings of the policy server and its workers (YAML section ``policy`` / ``worker``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, get_args

from pydantic import AfterValidator, BeforeValidator, Field, field_validator, model_validator

from services.core.config import Frozen, LogLevel, checked_names
from services.policy.transport import bad_target

# how a request's views are put on workers (WorkerPool.place; `viewscale serve --placement`)
Placement = Literal["auto", "pack", "spread"]
PLACEMENTS: tuple[str, ...] = get_args(Placement)

# what the model's passes compute in: float32, or bfloat16 autocast (ModelEngine; `--precision`)
Precision = Literal["fp32", "bf16"]
PRECISIONS: tuple[str, ...] = get_args(Precision)

# farthest a request's end effector may be from the robot's base (ServerConfig.max_reach_m): far
# past any arm's reach, short of a position given in millimetres (450 mm read as 450 m) or of one
# that overflows the model's float32 passes into a chunk that is not finite
MAX_REACH_M = 10.0


def _host_port(value: object) -> str:
    value = str(value)  # (a bare port arrives from YAML as an int)
    host, sep, port = value.rpartition(":")
    if not sep or not host or not port.isdigit() or int(port) > 65535:
        # (grpc would take port 99999 as 34463 without a word)
        raise ValueError(f"{value!r} is not host:port with a port of 0-65535 (e.g. 127.0.0.1:50051; 0: any free port)")
    return value


# where a server listens: host:port (a name, an IPv4 address, or [IPv6])
Listen = Annotated[str, BeforeValidator(_host_port)]


def _token(value: str | None) -> str | None:
    if value is not None and not value.strip():  # (it would turn the check off without a word)
        raise ValueError("is empty: give one, or leave it out for none")
    return value


# a bearer token; never "" (an empty one would mean: no token)
Token = Annotated[str | None, AfterValidator(_token)]


def open_to_others(listen: str) -> bool:
    """Whether host:port listens beyond this machine's loopback."""
    host = listen.rpartition(":")[0].strip("[]")
    return host not in ("127.0.0.1", "localhost", "::1") and not host.startswith("127.")


class TlsConfig(Frozen):
    cert: str | None = None  # PEM certificate chain of this server
    key: str | None = None  # its PEM private key
    ca: str | None = None  # PEM CA to verify the workers' certificates with (fan-out over TLS)

    @property
    def enabled(self) -> bool:
        return bool(self.cert and self.key)

    @model_validator(mode="after")
    def _pair(self) -> TlsConfig:
        if bool(self.cert) != bool(self.key):
            raise ValueError("tls needs both cert and key")
        for name in ("cert", "key", "ca"):
            path = getattr(self, name)
            if path and not Path(path).is_file():
                raise ValueError(f"tls.{name} {path}: no such file")
        return self


class WorkerConfig(Frozen):
    checkpoint: str  # checkpoint folder or run directory (its latest checkpoint)
    listen: Listen = "127.0.0.1:0"  # host:port; port 0 = the OS picks one (printed on the ready line)
    device: str = "cpu"  # cpu, cuda, cuda:N
    threads: int = Field(1, ge=1)  # intra-op threads of the model (1 measured fastest per worker on 2 cores)
    # bf16: the passes under bfloat16 autocast (a GPU's fast path); the server's setting must match
    precision: Precision = "fp32"
    max_batch: int = Field(64, ge=1)  # items at most in one forward pass
    max_streams: int = Field(256, ge=1)  # Denoise streams at once (a thread each); more: RESOURCE_EXHAUSTED
    group_wait_ms: float = Field(50.0, gt=0)  # longest a view waits for its request's other views here
    token: Token = None  # bearer token callers must present (the server's)
    tls: TlsConfig = TlsConfig()  # serve over TLS
    max_message_mb: int = Field(16, ge=1)  # gRPC message size cap, both ways
    log_level: LogLevel = "INFO"  # logging level of the process


class ServerConfig(Frozen):
    checkpoint: str  # checkpoint folder or run directory (its latest checkpoint)
    listen: Listen = "127.0.0.1:50051"  # host:port; loopback unless you mean it (0.0.0.0 = every interface)
    views: list[str] | None = None  # cameras composed when a request names none (default: the training views)
    rig: str | None = None  # rig preset or YAML: cameras added, or in place of the checkpoint's (recalibrated)
    task: str | None = None  # with rig: the task whose framing a sim rig takes (default: the checkpoint's)
    workers: int = Field(0, ge=0)  # local worker processes to start (0 with no addresses: in-process)
    worker: list[str] = Field(default_factory=list)  # addresses of running workers (host:port, or dns:///name:port)
    in_process: bool = False  # compute every view in this process even when workers are given
    # a request's views on workers: pack (all on one: one forward pass), spread (one each: passes
    # side by side), auto (spread over GPUs and machines, packed on the CPU workers that share cores)
    placement: Placement = "auto"
    device: str = "cpu"  # device of the in-process model and of local workers
    threads: int = Field(1, ge=1)  # intra-op threads of each model
    # bf16: the model's passes under bfloat16 autocast, in-process and in local workers; workers
    # that compute otherwise are not admitted (their answers would differ from the server's setting)
    precision: Precision = "fp32"
    token: Token = None  # bearer token: clients (and this server to its workers) present it
    tls: TlsConfig = TlsConfig()  # serve over TLS
    request_timeout_s: float = Field(5.0, gt=0)  # deadline of a GetAction whose call carries none
    worker_ready_s: float = Field(120.0, gt=0)  # how long to wait for the first worker to be ready
    # a worker connection that has read nothing this long is pinged, and closed when the ping goes
    # unanswered as long again: a frozen or cut-off replica behind a balanced address is left
    worker_keepalive_s: float = Field(5.0, ge=1.0)
    max_sessions: int = Field(256, ge=1)  # robot sessions kept (idle ones are forgotten first)
    # a request's end effector farther than this from the base (m) is refused: INVALID_ARGUMENT
    max_reach_m: float = Field(MAX_REACH_M, gt=0, allow_inf_nan=False)
    max_message_mb: int = Field(16, ge=1)  # gRPC message size cap, both ways
    log_level: LogLevel = "INFO"  # logging level of the process

    @field_validator("worker")
    @classmethod
    def _workers(cls, addresses: list[str]) -> list[str]:
        for a in addresses:
            if why := bad_target(a):
                raise ValueError(f"{a}: {why}")
        return addresses

    @field_validator("views")
    @classmethod
    def _views(cls, views: list[str] | None) -> list[str] | None:
        return checked_names(views, "names no camera (leave it out for the training views)")
