#!/usr/bin/env python3
"""Two commands timed as whole processes, in turn, with the ratio A / B pair by pair.

  python3 eval/bench/process_pair.py [--reps 7] [--warmup 1] -- 'COMMAND A' 'COMMAND B'

Each command is one string split as a shell splits words (no shell runs it; its output is discarded). After
--warmup runs of each, the two run in turn (A B A B ...) --reps times. For each: the median, minimum and
maximum of its CPU time (user + system of the finished process and its children), its wall time and its
peak resident memory; then the median of the pairs' ratios A / B of CPU and wall time, so that a drift of
the machine's speed during the runs cancels. Needs nothing beyond Python's standard library.
"""
import argparse
import os
import shlex
import statistics
import subprocess
import sys
import time


def run(argv):
    """Runs argv to completion; returns (cpu seconds, wall seconds, peak resident MiB, exit status)."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)  # reaped here, for its own resource usage
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)  # so that Popen does not wait for it again
    return usage.ru_utime + usage.ru_stime, wall, usage.ru_maxrss / 1024.0, proc.returncode


def row(name, values, unit):
    return "%-10s %10.3f %10.3f %10.3f %s" % (name, statistics.median(values), min(values), max(values), unit)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--reps", type=int, default=7, help="counted runs of each command (default 7)")
    parser.add_argument("--warmup", type=int, default=1, help="runs of each first, not counted (default 1)")
    parser.add_argument("commands", nargs=2, metavar="COMMAND", help="command A, then command B")
    args = parser.parse_args()
    if args.reps < 1 or args.warmup < 0:
        parser.error("--reps must be at least 1 and --warmup at least 0")
    argvs = [shlex.split(c) for c in args.commands]
    for argv in argvs:
        if not argv:
            parser.error("an empty command")
    for _ in range(args.warmup):
        for argv in argvs:
            run(argv)
    results = {"A": [], "B": []}
    failed = 0
    for _ in range(args.reps):
        for name, argv in zip("AB", argvs):
            cpu, wall, peak, status = run(argv)
            failed += status != 0
            results[name].append((cpu, wall, peak))
    print("%d runs of each, in turn, after %d not counted; median, min, max" % (args.reps, args.warmup))
    for name, command in zip("AB", args.commands):
        r = results[name]
        print("%s: %s" % (name, command if len(command) < 200 else command[:197] + "..."))
        print(row("  cpu", [x[0] for x in r], "s"))
        print(row("  wall", [x[1] for x in r], "s"))
        print(row("  peak", [x[2] for x in r], "MiB"))
    pairs = list(zip(results["A"], results["B"]))
    print(row("A/B cpu", [a[0] / b[0] for a, b in pairs if b[0] > 0], ""))
    print(row("A/B wall", [a[1] / b[1] for a, b in pairs if b[1] > 0], ""))
    if failed:
        print("%d runs exited with a non-zero status" % failed)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
