"""Start-up cost: the CPU a gateway spends from its launch to `/readyz` answering 200.

Usage: python -m bench.startup [--rounds 5] [--vehicles 10]

Each round starts `eqgw serve --simulate N` on a fresh SQLite file (migrations included) and
reads the process's CPU time (user + system, /proc) when `/readyz` first answers 200, then the
CPU of `import eqgw.main` alone in a fresh interpreter. Baselines taken in the same run, on the
same interpreter: an empty `python -c pass`, and `import asammdf` (the `mf4` extra, which eqgw
loads only when an MF4 log is read or written). Prints the median and the spread of each. CPU
time, not wall time: it is what a gateway costs its machine, and it varies less than the wall
clock on a shared one.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import httpx

from tests.proc_helpers import Process, eqgw, free_port, wait_until

TICK = os.sysconf("SC_CLK_TCK")


def _proc_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def serve_to_ready(tmp: Path, vehicles: int) -> float:
    """CPU seconds of `eqgw serve --simulate N` from its launch until /readyz is 200."""
    port = free_port()
    env = {"EQGW_DATABASE_URL": f"sqlite:///{tmp / 'eqgw.db'}", "EQGW_API_PORT": str(port)}
    gw = Process(eqgw("serve", "--simulate", str(vehicles)), tmp, env)

    def ready_cpu() -> float | None:
        """The process's CPU once /readyz is 200 (read at once), else None."""
        if gw.proc.poll() is not None:
            raise SystemExit(f"eqgw serve ended before it was ready: {gw.output()[-2000:]}")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return _proc_cpu(gw.proc.pid)
        except httpx.HTTPError:
            pass
        return None

    try:
        cpu: float = wait_until(ready_cpu, 120, "eqgw serve ready", interval=0.02)
        return cpu
    finally:
        gw.stop()


def python_cpu(code: str) -> tuple[float, int]:
    """CPU seconds of a fresh interpreter running `code` (its children's rusage), and its
    exit status."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    status = subprocess.run([sys.executable, "-c", code], check=False).returncode
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), status


def _line(label: str, values: list[float]) -> str:
    return (
        f"  {label:<44} {statistics.median(values):6.2f} s CPU"
        f"  (min {min(values):.2f}, max {max(values):.2f})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--vehicles", type=int, default=10)
    args = ap.parse_args()
    ready: list[float] = []
    imports: list[float] = []
    empty: list[float] = []
    asammdf: list[float] = []
    check = "import sys, eqgw.main; sys.exit('asammdf' in sys.modules)"
    for n in range(args.rounds):
        with tempfile.TemporaryDirectory(prefix="eqgw-startup-") as tmp:
            ready.append(serve_to_ready(Path(tmp), args.vehicles))
        cpu, loaded_asammdf = python_cpu(check)
        imports.append(cpu)
        empty.append(python_cpu("pass")[0])
        cpu, missing = python_cpu("import asammdf")
        if not missing:  # the mf4 extra is installed
            asammdf.append(cpu)
        print(f"round {n + 1}: ready after {ready[-1]:.2f} s CPU", flush=True)
    print(f"eqgw serve --simulate {args.vehicles}, {args.rounds} rounds, fresh SQLite each:")
    print(_line("launch to /readyz 200", ready))
    print(_line("import eqgw.main (fresh interpreter)", imports))
    print(f"  asammdf imported by import eqgw.main: {'yes' if loaded_asammdf else 'no'}")
    print(_line("baseline: python -c pass", empty))
    if asammdf:
        print(_line("baseline: import asammdf (deferred by eqgw)", asammdf))


if __name__ == "__main__":
    main()
