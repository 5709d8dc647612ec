"""Start-up time of the command line: `softplot --help` and `softplot cameras`, each as a new
process (what a user waits for), median over --repeat runs.

    .venv/bin/python tools/bench_cli.py --repeat 15
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

CASES = {
    "softplot --help": ["--help"],
    "softplot cameras": ["cameras"],
    "softplot detect --help": ["detect", "--help"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=15, help="runs per case (default 15)")
    args = ap.parse_args()
    for label, argv in CASES.items():
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "softplot", *argv], check=True,
                           stdout=subprocess.DEVNULL)
            times.append(time.perf_counter() - t0)
        print(f"{label:<26} median {statistics.median(times):.3f} s  "
              f"min {min(times):.3f} s  max {max(times):.3f} s  ({args.repeat} runs)")


if __name__ == "__main__":
    main()
