"""Regenerate services/pb/*_pb2.py from proto/services/pb/*.proto (run: python proto/gen.py).

The proto path mirrors the generated module path, so protoc writes imports such as
``from services.pb import common_pb2`` that resolve from the repository root.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import grpc_tools
from grpc_tools import protoc

ROOT = Path(__file__).resolve().parent.parent
PROTO = ROOT / "proto"


def generate(out_dir: Path = ROOT) -> list[Path]:
    sources = sorted((PROTO / "services" / "pb").glob("*.proto"))
    include = Path(grpc_tools.__file__).parent / "_proto"
    base = ["grpc_tools.protoc", f"-I{PROTO}", f"-I{include}"]
    messages = [*base, f"--python_out={out_dir}", f"--pyi_out={out_dir}", *[str(s) for s in sources]]
    if protoc.main(messages) != 0:
        raise SystemExit("protoc failed")
    # gRPC stubs only for files that declare a service (the rest would be empty modules).
    with_services = [str(s) for s in sources if re.search(r"^service\s", s.read_text(), re.MULTILINE)]
    if with_services and protoc.main([*base, f"--grpc_python_out={out_dir}", *with_services]) != 0:
        raise SystemExit("protoc (grpc) failed")
    return sources


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT
    for src in generate(out):
        print(f"generated from {src.relative_to(ROOT)}")
