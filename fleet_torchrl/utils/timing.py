"""Time one step of ``make experiments``: ``python -m fleet_torchrl.utils.timing STEP -- CMD ...``.

Runs CMD, then records its wall time, exit code and the machine in ``results/timings.json``
(atomically; other steps' entries are kept) for the report. Exits with CMD's exit code.
"""

from __future__ import annotations

import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from .runinfo import machine_summary, read_json, write_json

TIMINGS = Path("results/timings.json")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) < 3 or argv[1] != "--":
        print("usage: python -m fleet_torchrl.utils.timing STEP -- CMD ...", file=sys.stderr)
        return 2
    step, cmd = argv[0], argv[2:]
    t0 = time.perf_counter()
    rc = subprocess.run(cmd).returncode
    wall = time.perf_counter() - t0
    timings = read_json(TIMINGS) if TIMINGS.exists() else {}
    timings[step] = {"wall_s": round(wall, 1), "exit_code": rc,
                     "finished": datetime.now(UTC).isoformat(timespec="seconds"),
                     "machine": machine_summary()}
    write_json(TIMINGS, timings)
    print(f"[timing] {step}: {wall:.0f} s (exit {rc})")
    return rc


if __name__ == "__main__":
    sys.exit(main())
