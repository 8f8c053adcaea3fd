"""Ctrl-C (SIGINT) during a long `preston.solve` raises KeyboardInterrupt promptly, instead of once
the solve has ended."""

import os
import signal
import subprocess
import sys
import time

import pytest

from conftest import DATA

#: Longest time from the signal to the process's exit, s (the engine asks for a stop at every
#: progress report; the bound leaves room for a loaded machine and the interpreter's exit).
EXIT_AFTER_SIGNAL_MAX_S = 2.0

# Solves the sample job with a tolerance it cannot meet and no time limit, so that the solve
# runs far longer than the test waits; says when the solver iterates.
CHILD = r"""
import sys
import preston

said = []

def progress(event):
    if event["event"] == "iteration" and not said:
        said.append(True)
        print("iterating", flush=True)

try:
    preston.solve(sys.argv[1], progress=progress, tolerance=1e-15, max_iterations=10**7)
except KeyboardInterrupt:
    print("KeyboardInterrupt", flush=True)
    sys.exit(42)
print("finished", flush=True)
"""


@pytest.mark.skipif(os.name == "nt", reason="SIGINT to a child process is POSIX")
def test_ctrl_c_stops_a_long_solve_with_keyboard_interrupt():
    p = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(DATA / "job.toml")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert p.stdout.readline() == "iterating\n", p.stderr.read()
        # Well inside the solve.
        time.sleep(0.5)
        assert p.poll() is None, "the solve ended before the signal"
        sent = time.monotonic()
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=60)
        waited = time.monotonic() - sent
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 42, (out, err)
    assert out == "KeyboardInterrupt\n", (out, err)
    assert waited <= EXIT_AFTER_SIGNAL_MAX_S, f"{waited:.2f} s from SIGINT to exit"
