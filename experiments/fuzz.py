"""Long fuzzing run: the hypothesis tests of tests/test_fuzz.py with fresh random cases.

    python experiments/fuzz.py --cases 100000            # ~ hours on 2 cores
    python experiments/fuzz.py --cases 5000 -k improve   # only the improve() tests

Runs pytest on tests/test_fuzz.py with ``JTET_FUZZ_PROFILE=long`` (random, not the
derandomized CI replay) and ``JTET_FUZZ_CASES`` split over the tests by their weights,
prints hypothesis' per-test statistics and a summary table (cases run, failing, seconds).
A failure prints the falsifying ``MeshSpec`` and options; rebuild the mesh with
``tests/strategies.build_mesh`` and add it to tests/test_regressions.py.

Exit code: pytest's (0 when every case passed).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=100_000, help="total cases (default 100000)")
    ap.add_argument("-k", default=None, help="pytest -k expression to pick tests")
    ap.add_argument("--seed", type=int, default=None, help="hypothesis seed (default: random)")
    ap.add_argument("-x", action="store_true", help="stop at the first failing test")
    args = ap.parse_args(argv)

    env = dict(os.environ, JTET_FUZZ_PROFILE="long", JTET_FUZZ_CASES=str(args.cases))
    cmd = [sys.executable, "-m", "pytest", "-q", str(ROOT / "tests" / "test_fuzz.py")]
    cmd += ["--hypothesis-show-statistics", "-p", "no:cacheprovider"]
    if args.k:
        cmd += ["-k", args.k]
    if args.seed is not None:
        cmd += [f"--hypothesis-seed={args.seed}"]
    if args.x:
        cmd += ["-x"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    sys.stdout.write(proc.stdout)
    sys.stderr.write(proc.stderr)

    # one row per test from hypothesis' statistics
    rows = []
    blocks = re.split(r"\n(?=tests/test_fuzz\.py::\w+:)", proc.stdout)
    for block in blocks:
        m = re.match(r"tests/test_fuzz\.py::(\w+):", block)
        if not m:
            continue
        passing = sum(int(x) for x in re.findall(r"(\d+) passing", block))
        failing = sum(int(x) for x in re.findall(r"(\d+) failing", block))
        secs = sum(float(x) for x in re.findall(r"phase \(([\d.]+) seconds\)", block))
        rows.append((m.group(1), passing, failing, secs))
    if rows:
        print(f"\n{'test':42s} {'passing':>9s} {'failing':>8s} {'seconds':>9s}")
        for name, p, f, s in rows:
            print(f"{name:42s} {p:9d} {f:8d} {s:9.1f}")
        print(
            f"{'total':42s} {sum(r[1] for r in rows):9d} {sum(r[2] for r in rows):8d} "
            f"{seconds:9.1f}"
        )
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
