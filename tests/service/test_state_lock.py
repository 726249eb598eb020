"""One service per state directory: a second one on the same directory stops at start with one
line naming the directory and the holder's pid, instead of overwriting the first one's learned
state; the lock goes with the process that held it, however that process ends."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest
from svc_testlib import edge_raw, env, write_yaml

from thermal_edge.config import load_config
from thermal_edge.service.persistence import LOCKNAME, StateDirInUse, StateLock
from thermal_edge.service.service import EdgeService

#: an independent holder: flock on the lock file from another process, then wait
HOLDER = """
import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)
fcntl.flock(fd, fcntl.LOCK_EX)
os.ftruncate(fd, 0); os.write(fd, f"{os.getpid()}\\n".encode())
print("held", flush=True)
time.sleep(120)
"""


def _hold(lock: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(lock)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_service_on_a_held_state_directory_stops_at_start(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    cfg_path = write_yaml(tmp_path / "edge.yaml", edge_raw(state, {"interface": "virtual", "channel": "lock-test"},
                                                           table4=False, adapt=False))
    holder = _hold(state / LOCKNAME)
    try:
        with pytest.raises(StateDirInUse) as err:
            EdgeService(load_config(cfg_path), serve_metrics=False)
        assert str(err.value).startswith(f"state.dir {state}: in use by another thermal-edge (pid {holder.pid})")
        assert not (state / "state.json").exists()
        # the command: exit 2 and one line, before it opens the bus
        r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "run", "--config", str(cfg_path)],
                           capture_output=True, text=True, env=env(), timeout=120)
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip().splitlines()[-1].startswith(f"thermal-edge run: error: state.dir {state}: in use"), r.stderr
    finally:
        holder.kill()
        holder.wait()
    # killed: the kernel dropped its lock, and a service takes the directory
    svc = EdgeService(load_config(cfg_path), serve_metrics=False)
    assert svc.state_lock.held and (state / LOCKNAME).read_text().strip() == str(__import__("os").getpid())


def test_the_lock_is_released_for_the_next_process_and_shared_within_one(tmp_path: Path) -> None:
    a, b = StateLock(tmp_path), StateLock(tmp_path)
    assert a.acquire() and b.acquire()  # one process is one service: counted, not refused
    a.release()
    probe = [sys.executable, "-c", "import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDWR); "
             "fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)", str(tmp_path / LOCKNAME)]
    assert subprocess.run(probe, capture_output=True, timeout=60).returncode != 0  # b still holds it
    b.release()
    t0 = time.monotonic()
    assert subprocess.run(probe, capture_output=True, timeout=60).returncode == 0, time.monotonic() - t0


def test_a_directory_that_cannot_hold_a_lock_file_is_not_locked(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert StateLock(blocker).acquire() is False  # the store reports it cannot save; protection goes on
