"""The stop guard (``io.atomic.guard_stopping``): a command-line process that a signal did not stop, its main
thread blocked where the interruption cannot reach, still ends in bounded time, one line said, its temporary
outputs removed; a command finishing with its outputs in place is not cut."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(os.name != "posix", reason="signals as POSIX sends them")

_REPO = Path(__file__).resolve().parents[1]

_PRELUDE = """
import sys, threading, time
from pathlib import Path
from warp_highlights.io import atomic
atomic.STOP_GRACE_SECONDS = 1.0
atomic.handle_termination(hold_after_output=True)
atomic.guard_stopping()
out = Path(sys.argv[1])
"""

_BLOCKED = """
with atomic.atomic_file(out, overwrite=False) as temporary:
    temporary.write_text("half")
    lock = threading.Lock()
    lock.acquire()
    try:  # the signal may come while "ready" is still being printed: lost too
        print("ready", flush=True)
    except KeyboardInterrupt:
        pass
    while True:  # a main thread that never stops: every interruption it is given is lost
        try:
            lock.acquire()
        except KeyboardInterrupt:
            pass
"""

_FINISHING = """
with atomic.atomic_file(out, overwrite=False) as temporary:
    temporary.write_text("whole")
print("ready", flush=True)  # the output is in place: signals are held until the command ends
time.sleep(3.0)  # the rest of the command, three times the grace
print("held", atomic.end_of_command(), flush=True)
"""


def _start(body: str, out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(_REPO), os.environ.get("PYTHONPATH")])))
    process = subprocess.Popen([sys.executable, "-c", textwrap.dedent(_PRELUDE + body), str(out)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert process.stdout.readline().strip() == "ready", process.stderr.read()
    return process


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_process_whose_main_thread_does_not_stop_is_ended_with_its_partial_output_removed(tmp_path, signum):
    out = tmp_path / "out.txt"
    process = _start(_BLOCKED, out)
    assert [p.name for p in tmp_path.iterdir() if ".partial-" in p.name]  # the temporary output exists
    sent = time.monotonic()
    process.send_signal(signum)
    try:
        stdout, stderr = process.communicate(timeout=20)
    finally:
        process.kill()
    assert process.returncode == 128 + signum
    assert time.monotonic() - sent < 10
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "had not stopped 1 s later and was ended" in lines[0], stderr
    assert ("SIGTERM" in lines[0]) == (signum == signal.SIGTERM)
    assert list(tmp_path.iterdir()) == []  # neither the output nor its temporary


def test_a_command_finishing_with_its_outputs_in_place_is_not_cut(tmp_path):
    out = tmp_path / "out.txt"
    process = _start(_FINISHING, out)
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=20)
    assert process.returncode == 0, stderr
    assert stdout.strip() == f"held {int(signal.SIGINT)}" and stderr == ""
    assert out.read_text() == "whole"


_FORKING = """
import os, signal
child = os.fork()
if child == 0:  # the child takes the signal (its handler raises there) and ends
    try:
        time.sleep(10)
    finally:
        os._exit(0)
print("ready", flush=True)
os.kill(child, signal.SIGTERM)
os.waitpid(child, 0)
time.sleep(2.5)  # more than the grace: a guard that took the child's signal for its own would end this process
print("alive", flush=True)
"""


def test_a_forked_child_s_signal_is_not_taken_for_the_process_s_own(tmp_path):
    process = _start(_FORKING, tmp_path / "out.txt")
    stdout, stderr = process.communicate(timeout=20)
    assert process.returncode == 0, stderr
    assert stdout.strip() == "alive"
