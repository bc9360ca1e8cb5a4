"""The checked-in generated code is exactly what proto/gen.py makes from proto/."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_generated_code_is_up_to_date(tmp_path):
    spec = importlib.util.spec_from_file_location("proto_gen", ROOT / "proto" / "gen.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    sources = gen.generate(tmp_path)
    assert sources, "no .proto files found"
    fresh = sorted(p.relative_to(tmp_path) for p in (tmp_path / "services" / "pb").glob("*_pb2*"))
    checked_in = sorted(p.relative_to(ROOT) for p in (ROOT / "services" / "pb").glob("*_pb2*"))
    assert fresh == checked_in, "generated files differ from checked-in ones: run `make proto`"
    for rel in fresh:
        assert (tmp_path / rel).read_bytes() == (ROOT / rel).read_bytes(), f"{rel} is stale: run `make proto`"
