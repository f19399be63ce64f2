"""Run every benchmarks/bench_*.py in turn (`make bench`); each prints its own figures."""

import platform
import os
import runpy
import sys
from pathlib import Path

here = Path(__file__).parent
print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
for script in sorted(here.glob("bench_*.py")):
    print(f"\n== {script.stem} ==", flush=True)
    runpy.run_path(str(script), run_name="__main__")
sys.exit(0)
