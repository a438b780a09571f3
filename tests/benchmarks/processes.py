"""Running a benchmark case in a fresh process: its wall time and its own peak memory."""

from __future__ import annotations

import json
import subprocess
import sys
import time

# The peak resident memory of this process alone. Linux's ru_maxrss also counts the peak
# of the process that started it (kept across fork and exec), which here is the
# benchmark itself with the simulated data; VmHWM belongs to the process's own memory.
PEAK = r"""
import resource
def peak_kb():
    try:
        with open("/proc/self/status") as status:
            return next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
"""


def run(code: str, *args: str) -> dict:
    """One case in a fresh process (its code prints a JSON line last); its wall time
    includes start-up and imports."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    result["seconds"] = time.perf_counter() - start
    return result
