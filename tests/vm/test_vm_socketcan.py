"""Real SocketCAN in the qemu VM: the kernel, can-utils, cantools and python-can on vcan0.

Each test is one boot-run-poweroff of the VM (see conftest.py / vmrun.py); the
frames carry a valid alive counter and CRC as the CAN matrix defines them,
computed here on the host independently of the package's codec.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import vmrun  # tests/vm is on sys.path (conftest.py)

VENV_PY = vmrun.DEFAULT_PYTHON
DBC = str(Path(vmrun.DEFAULT_CWD) / "dbc" / "thermal_edge.dbc")

#: Shell snippet: wait until some socket receives everything on vcan0, i.e. candump has bound.
WAIT_FOR_RECEIVER = vmrun.SH_WAIT_FOR_RECEIVER


def crc8_sae_j1850(data: bytes) -> int:
    """CRC-8/SAE-J1850: poly 0x1D, init 0xFF, xorout 0xFF, no reflection."""
    reg = 0xFF
    for byte in data:
        reg ^= byte
        for _ in range(8):
            reg = ((reg << 1) ^ 0x1D) & 0xFF if reg & 0x80 else (reg << 1) & 0xFF
    return reg ^ 0xFF


def protected_frame(can_id: int, fields: list[tuple[int, int, int]], counter: int) -> bytes:
    """8 data bytes: Intel-order raw ``fields`` (start bit, length, raw value), counter at bit 48, CRC byte 7."""
    word = 0
    for start, length, raw in fields:
        word |= (raw & ((1 << length) - 1)) << start
    word |= (counter & 0xF) << 48
    payload = word.to_bytes(7, "little")
    data_id = 0x1000 + can_id
    return payload + bytes([crc8_sae_j1850(bytes([data_id & 0xFF, data_id >> 8]) + payload)])


def temp_raw(deg_c: float) -> int:
    return round((deg_c + 50.0) / 0.1)


# INV_Currents: Id 10 A, Iq -20 A, IphRms 25 A, counter 3.
CURRENTS = protected_frame(0x0A0, [(0, 16, 200), (16, 16, -400), (32, 16, 500)], counter=3)
# INV_StatorTemps: slot 80.0 °C, end winding 85.5 °C, housing 40.0 °C, all valid; counter 7.
STATOR = protected_frame(
    0x0B0, [(0, 12, temp_raw(80.0)), (12, 12, temp_raw(85.5)), (24, 12, temp_raw(40.0))], counter=7
)


def test_crc_matches_catalogue_check_value():
    assert crc8_sae_j1850(b"123456789") == 0x4B


def test_vm_boots_distribution_kernel_with_vcan0(vm):
    res = vm.run(
        "uname -r; echo @@; cat /proc/version; echo @@; ip -details link show vcan0; echo @@; "
        "cat /sys/class/net/vcan0/type; echo @@; grep -c . /proc/modules; lsmod | grep -E '^(vcan|can_raw|can) '",
        timeout=90,
    ).check()
    release, version, link, arphrd, _ = (part.strip() for part in res.stdout.split("@@", 4))
    # A distribution kernel: the one installed under /boot with its /lib/modules, not the host's.
    assert release == vm.kernel.version == res.kernel
    assert Path(f"/boot/vmlinuz-{release}").is_file() and Path(f"/lib/modules/{release}").is_dir()
    assert re.fullmatch(r"\d+\.\d+\.\d+-\d+-[a-z0-9]+", release), release
    assert "Debian" in version, version
    assert "vcan0" in link and "link/can" in link and re.search(r"\bvcan\b", link), link
    assert "UP" in link.splitlines()[0], link
    assert arphrd == "280"  # ARPHRD_CAN
    assert "vcan" in res.stdout and "can_raw" in res.stdout
    print(f"guest kernel {release} ({res.accel}); boot {res.boot_seconds:.1f} s, wall {res.wall_seconds:.1f} s")


#: ``python -m cantools`` without matplotlib: its ``plot`` subcommand imports
#: matplotlib.pyplot at start-up, 15-25 s under software emulation; blocked, it
#: just makes ``plot`` unavailable.  Arguments follow as for ``-m cantools``.
CANTOOLS_MAIN = (
    "import runpy, sys; sys.modules['matplotlib'] = None; "
    "runpy.run_module('cantools', run_name='__main__', alter_sys=True)"
)


def test_can_utils_round_trip_and_cantools_decode(vm):
    cmd = f"""
set -e
timeout 30 candump -L -n 2 vcan0 > /tmp/dump.log &
DUMP=$!
{WAIT_FOR_RECEIVER}
cansend vcan0 0A0#{CURRENTS.hex().upper()}
cansend vcan0 0B0#{STATOR.hex().upper()}
wait $DUMP
echo @@DUMP; cat /tmp/dump.log
echo @@DECODE
{VENV_PY} -c {shlex.quote(CANTOOLS_MAIN)} decode {DBC} < /tmp/dump.log
"""
    res = vm.run(cmd, timeout=150).check()
    dump, decoded = res.stdout.split("@@DUMP", 1)[1].split("@@DECODE", 1)
    frames = re.findall(r"^\(\d+\.\d+\) vcan0 ([0-9A-F]{3})#([0-9A-F]*)$", dump.strip(), re.M)
    assert frames == [("0A0", CURRENTS.hex().upper()), ("0B0", STATOR.hex().upper())], dump
    text = " ".join(decoded.split())
    assert "INV_Currents(" in text and "INV_StatorTemps(" in text, decoded
    for expect in (
        "INV_Id: 10.0 A",
        "INV_Iq: -20.0 A",
        "INV_IphRms: 25.0 A",
        "INV_Currents_Counter: 3",
        f"INV_Currents_CRC: {CURRENTS[7]}",
        "INV_T_WindingSlot: 80.0",
        "INV_T_EndWinding: 85.5",
        "INV_T_Housing: 40.0",
        "INV_StatorTemps_Counter: 7",
        f"INV_StatorTemps_CRC: {STATOR[7]}",
    ):
        assert expect in text, f"{expect!r} not in cantools output:\n{decoded}"


# Runs in the guest with the project's venv: python-can sends 10 protected TE_Limits
# frames that candump counts, then receives the frames cansend puts on vcan0.
_PYCAN_SCRIPT = r"""
import json, subprocess, sys, time
import can

expected = json.loads(sys.argv[1])
dump = subprocess.Popen(["timeout", "60", "candump", "-L", "-n", "10", "vcan0"],
                        stdout=subprocess.PIPE, text=True)
deadline = time.monotonic() + 20
def candump_bound():  # a receiver line for vcan0 ("(vcan0: no entry)" when there is none)
    with open("/proc/net/can/rcvlist_all") as fh:
        return any(line.split()[:1] == ["vcan0"] for line in fh)
while not candump_bound():
    assert time.monotonic() < deadline, "candump never bound to vcan0"
    time.sleep(0.05)
with can.Bus(interface="socketcan", channel="vcan0") as bus:
    for hexdata in expected["tx"]:
        bus.send(can.Message(arbitration_id=0x2A0, data=bytes.fromhex(hexdata), is_extended_id=False))
    dumped, _ = dump.communicate(timeout=60)
    for frame in expected["rx"]:
        subprocess.run(["cansend", "vcan0", frame], check=True)
    received = []
    while len(received) < len(expected["rx"]):
        msg = bus.recv(timeout=10)
        if msg is None:
            break
        received.append("%03X#%s" % (msg.arbitration_id, msg.data.hex().upper()))
print(json.dumps({"python_can": can.__version__, "candump": dumped.splitlines(),
                  "candump_rc": dump.returncode, "received": received}))
"""


def _te_limits(i: int) -> bytes:
    # TE_TorqueLimit 50.0+i Nm, TE_CurrentLimit 100 A, derate active with reason 1 on odd i.
    return protected_frame(
        0x2A0, [(0, 16, 500 + 10 * i), (16, 16, 2000), (32, 1, i % 2), (33, 4, i % 2)], counter=i
    )


def test_python_can_socketcan_exchanges_frames_with_can_utils(vm):
    tx = [_te_limits(i).hex().upper() for i in range(10)]
    rx = [f"0A1#{protected_frame(0x0A1, [(0, 16, 3000 + i), (16, 16, 150), (32, 16, 6000)], i).hex().upper()}"
          for i in range(3)]
    arg = json.dumps({"tx": tx, "rx": rx})
    res = vm.python(_PYCAN_SCRIPT, timeout=150, args=shlex.quote(arg)).check()
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["candump_rc"] == 0, out
    dumped = [line.split(" ", 2)[2] for line in out["candump"]]
    assert dumped == [f"2A0#{h}" for h in tx], out["candump"]
    assert out["received"] == rx, out


def test_pytest_selection_inside_vm(vm):
    """The harness path the service tests use: a pytest selection run in the guest."""
    # only pytest itself: autoloading the installed plugins (xdist, asyncio, ...) costs minutes under emulation
    res = vm.pytest("tests/vm/guest_socketcan_checks.py", timeout=180, env={"PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"})
    assert res.returncode == 0, res.describe()
    assert re.search(r"\b2 passed\b", res.stdout), res.describe()
