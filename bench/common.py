"""What every benchmark shares: the machine description and the RESULTS.md row.

Each benchmark prints exactly one JSON line on stdout and appends it, with the machine, the
date and the load average (1/5/15 min, at the end of the run), to bench/RESULTS.md.
"""

from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from pathlib import Path

from services.core.runtime import host_description  # bench scripts put the project root on sys.path

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"
HEADER = "# Benchmark results\n\nOne row per run, appended by the scripts in bench/ (newest last).\n\n"


def machine() -> str:
    gpu = "no GPU"
    try:
        import torch

        if torch.cuda.is_available():
            gpu = f"GPU {torch.cuda.get_device_name(0)}"
    except ImportError:
        pass
    return host_description(gpu)


def report(name: str, result: dict) -> dict:
    """Print the JSON line and append it to RESULTS.md; returns the full record."""
    record = {
        "bench": name,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        **result,
    }
    line = json.dumps(record, sort_keys=False)
    print(line, flush=True)
    if not RESULTS.exists():
        RESULTS.write_text(HEADER)
    with RESULTS.open("a") as fh:
        fh.write(
            f"- `{name}` {record['date']} on {record['machine']}, load {record['loadavg']}:\n  `{json.dumps(result)}`\n"
        )
    return record
