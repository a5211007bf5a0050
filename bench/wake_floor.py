"""The CPU one wake-up of a thread costs on this machine, after a sleep of 0, 2, 10
and 40 ms: the floor under any driver that wakes per byte or per frame.

One wake-up = sleep, write a byte to a pipe, select() on it, read it back (what a
driver does when a byte comes: the wait returns, the descriptor is read).  The CPU
is the thread's own (``time.thread_time()``, CLOCK_THREAD_CPUTIME_ID), divided by
the iterations.  The longer the sleep, the colder the caches and TLB the thread
comes back to, and the more a wake-up costs.  The C twin (compiled with gcc when
it is on the PATH, else left out) does the same with nanosleep/poll, so the
Python interpreter's share shows as the difference.

    python bench/wake_floor.py          # prints the table
"""

from __future__ import annotations

import argparse
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

SLEEPS_MS = (0.0, 2.0, 10.0, 40.0)
ITERATIONS = 200  # per sleep; 20000 without a sleep

C_SOURCE = r"""
#define _POSIX_C_SOURCE 200809L
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

static double cpu(void)
{
    struct timespec t;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}

int main(int argc, char **argv)
{
    int p[2];
    char buf[16];
    if (pipe(p) != 0)
        return 1;
    for (int k = 1; k < argc; k++) {
        double ms = atof(argv[k]);
        int n = ms > 0 ? ITERATIONS : 20000;
        double t0 = cpu();
        for (int i = 0; i < n; i++) {
            if (ms > 0) {
                struct timespec ts = {0, (long)(ms * 1e6)};
                nanosleep(&ts, NULL);
            }
            if (write(p[1], "x", 1) != 1)
                return 1;
            struct pollfd f = {p[0], POLLIN, 0};
            if (poll(&f, 1, 0) != 1 || read(p[0], buf, sizeof buf) != 1)
                return 1;
        }
        printf("%g %.3f\n", ms, (cpu() - t0) / n * 1e6);
    }
    return 0;
}
"""


def python_floor(sleeps_ms: tuple[float, ...] = SLEEPS_MS) -> dict[float, float]:
    """CPU µs per wake-up of this Python thread after each sleep."""
    r, w = os.pipe()
    out: dict[float, float] = {}
    try:
        for ms in sleeps_ms:
            n = ITERATIONS if ms else 20000
            t0 = time.thread_time()
            for _ in range(n):
                if ms:
                    time.sleep(ms / 1000.0)
                os.write(w, b"x")
                select.select([r], [], [], 0)
                os.read(r, 16)
            out[ms] = (time.thread_time() - t0) / n * 1e6
    finally:
        os.close(r)
        os.close(w)
    return out


def c_floor(sleeps_ms: tuple[float, ...] = SLEEPS_MS) -> dict[float, float] | None:
    """The same in C (None without gcc, or when it fails to build)."""
    gcc = shutil.which("gcc")
    if gcc is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "wake.c"
        exe = Path(tmp) / "wake"
        src.write_text(C_SOURCE.replace("ITERATIONS", str(ITERATIONS)))
        build = subprocess.run(
            [gcc, "-O2", "-std=c99", "-Wall", "-Wextra", "-o", str(exe), str(src)],
            capture_output=True,
            text=True,
        )
        if build.returncode != 0:
            print(f"(gcc failed, C left out: {build.stderr.strip()})")
            return None
        run = subprocess.run(
            [str(exe), *(str(ms) for ms in sleeps_ms)], capture_output=True, text=True, check=True
        )
    out: dict[float, float] = {}
    for line in run.stdout.split("\n"):
        if line.strip():
            ms, us = line.split()
            out[float(ms)] = float(us)
    return out


def table(py: dict[float, float], c: dict[float, float] | None) -> str:
    head = "| sleep before the wake-up | Python CPU µs/wake-up |"
    rule = "|---:|---:|"
    if c is not None:
        head += " C CPU µs/wake-up | Python / C |"
        rule += "---:|---:|"
    rows = [head, rule]
    for ms, us in py.items():
        row = f"| {ms:g} ms | {us:.1f} |"
        if c is not None and ms in c:
            row += f" {c[ms]:.1f} | {us / c[ms]:.1f}x |"
        rows.append(row)
    return "\n".join(rows)


def measure() -> str:
    """The table, Python first (C interleaved would share its caches)."""
    return table(python_floor(), c_floor())


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    py, c = python_floor(), c_floor()
    print(table(py, c))
    if args.json:
        out = {"sleeps_ms": list(py), "python_us": list(py.values())}
        out["c_us"] = [c.get(ms) for ms in py] if c is not None else None
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
