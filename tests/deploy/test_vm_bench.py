"""The manual's vcan0 bench (docs/guide/try-it.md) on real SocketCAN, in the project's qemu VM (tests/vm/vmrun.py):
``thermal-edge run`` on vcan0 under a fake systemd notify socket, the inverter emulator on vcan0 as
a second process in real time. Several minutes under software emulation; marked ``vm`` (and
skipped with the reason when the VM cannot be had)."""
from __future__ import annotations

import json
import sys

import deploylib as dl
import pytest

pytestmark = [pytest.mark.vm, pytest.mark.slow]


@pytest.fixture(scope="module")
def vm():  # the VM driver of tests/vm
    here = str(dl.REPO / "tests" / "vm")
    if here not in sys.path:
        sys.path.insert(0, here)
    import os

    if os.environ.get("THERMAL_EDGE_IN_VM") == "1":
        pytest.skip("already inside the VM")
    import vmrun

    try:
        return vmrun.VM().prepare()
    except vmrun.VMUnavailable as exc:
        pytest.skip(f"VM unavailable: {exc}")


@pytest.mark.timeout(1800)
def test_bench_on_vcan0(vm) -> None:
    py = dl.REPO / ".venv" / "bin" / "python"
    res = vm.run(f"{py if py.exists() else 'python3'} tests/deploy/guest_bench.py", timeout=1500)
    line = next((l for l in res.stdout.splitlines() if l.startswith("BENCH ")), None)
    assert line, f"no result (exit {res.returncode}):\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}"
    out = json.loads(line[len("BENCH "):])
    print({k: v for k, v in out.items() if not k.endswith("_log")})
    assert out["first_notifications"][:1] == ["READY"], out
    assert out["watchdog_pings"] >= 2 and out["last_notification"] == "STOPPING", out
    inverter_frames = ("INV_Currents", "INV_Mechanics", "INV_StatorTemps", "INV_AmbientTemps")
    assert all(out["received"].get(f, 0) > 0 for f in inverter_frames), out
    assert out["sent"].get("TE_Limits", 0) > 0, out
    assert out["dropped"] == 0, out
    assert out["ticks"] >= 10, out
    assert out["rc_service"] == 0 and out["state_saved"], out["service_log"]
