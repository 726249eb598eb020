"""Run commands against real SocketCAN (``vcan0``) inside a small qemu VM.

The host kernel of the development and CI machines has no SocketCAN, so this
driver boots a Debian distribution kernel under qemu with a tiny initramfs
built on the fly (busybox + the virtio, 9p and CAN modules), creates ``vcan0``
in the guest, mounts the host's root file system read-only over 9p, chroots
into it and runs one shell command line there -- with the host's own
programs, can-utils and the project's virtual environment.  The command's
exit status, stdout and stderr come back through a writable 9p share; the
guest then powers off.  Every run is bounded by a hard timeout after which
qemu is killed.

Importable::

    from vmrun import SH_WAIT_FOR_RECEIVER, VM, VMUnavailable
    vm = VM().prepare()          # finds everything, probes KVM, boots once; or VMUnavailable
    res = vm.run(f"candump -n 1 vcan0 & {SH_WAIT_FOR_RECEIVER}; cansend vcan0 123#00; wait", timeout=60)
    res.check()                  # AssertionError with all output unless exit status 0
    res = vm.pytest("tests/bus/test_bus_transport.py -k socketcan", timeout=300)  # pytest's exit status
    res = vm.python("import can; ...", timeout=120, args="...")                  # the venv's python
    res.returncode, res.stdout, res.stderr, res.kernel, res.console, res.artifacts, res.boot_seconds

Cost (measured on a 2-core machine, KVM unusable there so software emulation
``-accel tcg -cpu max``): boot to ready 5.5-10 s, boot+poweroff of a trivial
command 6-11 s (depends on host load).  Python under emulation is 10-50x
slower than on the host: ``import can`` ~3.5 s, numpy ~2.5 s, cantools ~8 s,
``import pytest`` ~10 s, ``scipy.signal`` ~30 s; ``python -m cantools`` also
imports matplotlib.pyplot (~15-25 s).  Batch checks into one run and give
generous timeouts.

Command line::

    python tests/vm/vmrun.py [--timeout S] [--cwd DIR] [--accel auto|kvm|tcg] -- CMD...

Inside the guest the command runs as root with ``cwd`` (default
the source tree this file belongs to), ``/tmp`` a fresh tmpfs, ``HOME=/tmp/home``, the host tree
read-only (Python writes no bytecode: ``PYTHONDONTWRITEBYTECODE=1``) and
``$VM_ARTIFACTS`` a writable directory whose files come back in
``Result.artifacts``; files given to ``run(files=...)`` are in ``$VM_FILES``.
``$THERMAL_EDGE_IN_VM=1`` tells code (and tests) that they run in the guest.

Environment knobs (host side): ``THERMAL_EDGE_VM=0`` disables the VM
(``prepare`` raises VMUnavailable), ``THERMAL_EDGE_VM_ACCEL=auto|kvm|tcg``,
``THERMAL_EDGE_VM_CACHE=DIR`` where initramfs images and the KVM probe
verdict are cached (default ``$TMPDIR/thermal_edge-vm-cache``),
``THERMAL_EDGE_VM_MEM`` (MiB, default 1536), ``THERMAL_EDGE_VM_SMP`` (vCPUs,
default min(2, host cores)), ``THERMAL_EDGE_VM_VERBOSE=1``
echoes the guest console to stderr while it runs.

The host's packages are never installed from here: ``make test-deps`` (as root, once per machine)
installs the Debian packages of :data:`APT_PACKAGES`; without them ``prepare`` raises
VMUnavailable naming what is missing and that target.

Only the standard library is used, so the driver runs with any python3 >= 3.9.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import fcntl
import gzip
import hashlib
import io
import lzma
import os
import re
import shlex
import shutil
import signal
import stat
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

__all__ = [
    "APT_PACKAGES",
    "MODULES",
    "Result",
    "SH_WAIT_FOR_RECEIVER",
    "VM",
    "VMUnavailable",
    "main",
]

#: Kernel modules for the guest, loaded in this order (plus any dependency the
#: kernel's modules.dep names, which is loaded first; built-in ones are skipped).
MODULES: tuple[str, ...] = (
    "virtio_ring",
    "virtio",
    "virtio_pci_legacy_dev",
    "virtio_pci_modern_dev",
    "virtio_pci",
    "netfs",
    "fscache",
    "9pnet",
    "9pnet_virtio",
    "9p",
    "can",
    "can-raw",
    "can-dev",
    "vcan",
)

#: Debian packages providing what the VM needs (what -> package).
APT_PACKAGES: dict[str, str] = {
    "qemu": "qemu-system-x86",
    "kernel": "linux-image-amd64",
    "busybox": "busybox-static",
    "can-utils": "can-utils",
}

#: Where the guest sees the writable share (inside the chroot).
GUEST_SHARE = "/tmp/vmshare"
#: scheduling priority of qemu when run as root (negative: before the host's other processes)
QEMU_NICE = -10
#: the source tree these tests belong to and its venv (the guest sees the host's root, so the same
#: paths): a clone elsewhere tests itself, not another checkout
DEFAULT_CWD = str(Path(__file__).resolve().parents[2])
DEFAULT_PYTHON = str(Path(DEFAULT_CWD) / ".venv" / "bin" / "python")
MARK = "@@VM:"

_HERE = Path(__file__).resolve().parent

#: Shell snippet for guest commands: wait (at most ~10 s) until some socket is bound to
#: receive everything on vcan0 (e.g. a ``candump vcan0 &`` started just before), so that
#: frames sent next are not lost to the race.  ``(vcan0: no entry)`` lines do not count.
SH_WAIT_FOR_RECEIVER = (
    "i=0; while ! grep -qsE '^ +vcan0 +[0-9A-Fa-f]+ ' /proc/net/can/rcvlist_all && [ $i -lt 100 ]; "
    "do sleep 0.1; i=$((i+1)); done"
)


class VMUnavailable(RuntimeError):
    """The VM cannot be had on this machine; ``str(exc)`` says why (for pytest.skip)."""


@dataclasses.dataclass
class Result:
    """Outcome of one command run in the VM."""

    cmd: str
    #: Exit status of the command in the guest; None when it did not finish
    #: (hard timeout, guest crash, boot failure).
    returncode: int | None
    stdout: str
    stderr: str
    #: ``uname -r`` of the guest ("" if it never got that far).
    kernel: str
    #: ``ip -details link show vcan0`` as printed in the guest.
    vcan: str
    #: Everything the guest printed on its serial console.
    console: str
    accel: str
    #: Seconds from starting qemu until the guest was ready to run the command
    #: (modules loaded, vcan0 up, host root mounted); None if never ready.
    boot_seconds: float | None
    #: Seconds the command itself took in the guest (host clock); None if unknown.
    cmd_seconds: float | None
    #: Seconds from starting qemu until it exited (or was killed).
    wall_seconds: float
    timed_out: bool
    #: Files the command wrote below ``$VM_ARTIFACTS`` (relative path -> bytes).
    artifacts: dict[str, bytes] = dataclasses.field(default_factory=dict)
    #: Guest-side problems reported on the console (``@@VM:ERROR ...`` lines).
    errors: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.returncode == 0

    @property
    def booted(self) -> bool:
        return self.boot_seconds is not None

    @property
    def output(self) -> str:
        return self.stdout + self.stderr

    def describe(self) -> str:
        """A report with everything useful to diagnose a failed run."""
        if self.timed_out:
            status = f"killed after the hard timeout ({self.wall_seconds:.1f} s)"
        elif self.returncode is None:
            status = "no exit status (guest did not finish the command)"
        else:
            status = f"exit status {self.returncode}"
        console_tail = "\n".join(self.console.splitlines()[-60:])
        return (
            f"VM command {self.cmd!r}: {status}; kernel {self.kernel or '?'}, accel {self.accel}, "
            f"boot {_fmt_s(self.boot_seconds)}, command {_fmt_s(self.cmd_seconds)}, "
            f"wall {self.wall_seconds:.1f} s\n"
            + (f"guest errors: {self.errors}\n" if self.errors else "")
            + f"--- stdout ---\n{self.stdout}\n--- stderr ---\n{self.stderr}\n"
            + f"--- console (tail) ---\n{console_tail}\n"
        )

    def check(self) -> Result:
        """Return self if the command exited 0, else raise AssertionError with the whole report."""
        if self.returncode != 0:
            raise AssertionError(self.describe())
        return self


def _fmt_s(value: float | None) -> str:
    return "?" if value is None else f"{value:.1f} s"


def _log(msg: str) -> None:
    print(f"[vm] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------- host tools


def _elf_is_static(path: Path) -> bool:
    """True if ``path`` is an ELF executable without a program interpreter."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
            if head[:4] != b"\x7fELF" or head[4] != 2:  # ELF64 only
                return False
            endian = "<" if head[5] == 1 else ">"
            phoff = struct.unpack_from(endian + "Q", head, 0x20)[0]
            phentsize, phnum = struct.unpack_from(endian + "HH", head, 0x36)
            fh.seek(phoff)
            table = fh.read(phentsize * phnum)
    except OSError:
        return False
    for i in range(phnum):
        (p_type,) = struct.unpack_from(endian + "I", table, i * phentsize)
        if p_type == 3:  # PT_INTERP
            return False
    return True


def find_busybox() -> Path | None:
    for cand in ("/bin/busybox", "/usr/bin/busybox", "/sbin/busybox", shutil.which("busybox")):
        if cand and Path(cand).is_file() and _elf_is_static(Path(cand)):
            return Path(cand).resolve()
    return None


def find_qemu() -> Path | None:
    found = shutil.which("qemu-system-x86_64")
    return Path(found) if found else None


def find_can_utils() -> Path | None:
    found = [shutil.which(t) for t in ("candump", "cansend", "cangen")]
    return Path(found[0]) if all(found) else None


def _version_key(ver: str) -> list:
    return [int(p) if p.isdigit() else p for p in re.split(r"[.\-+~]", ver)]


@dataclasses.dataclass(frozen=True)
class Kernel:
    version: str
    vmlinuz: Path
    moddir: Path


def _module_index(moddir: Path) -> tuple[dict[str, tuple[str, list[str]]], set[str]]:
    """modules.dep as {name: (relpath, [dep relpaths])} and the set of built-in names."""

    def name_of(rel: str) -> str:
        base = rel.rsplit("/", 1)[-1]
        base = re.sub(r"\.ko(\.(xz|zst|gz))?$", "", base)
        return base.replace("-", "_")

    deps: dict[str, tuple[str, list[str]]] = {}
    for line in (moddir / "modules.dep").read_text().splitlines():
        if ":" not in line:
            continue
        rel, rest = line.split(":", 1)
        deps[name_of(rel.strip())] = (rel.strip(), rest.split())
    builtin: set[str] = set()
    bfile = moddir / "modules.builtin"
    if bfile.is_file():
        builtin = {name_of(r.strip()) for r in bfile.read_text().splitlines() if r.strip()}
    return deps, builtin


def find_kernel() -> tuple[Kernel | None, str]:
    """The newest /boot/vmlinuz-<ver> whose /lib/modules/<ver> has vcan (and 9p); else (None, why)."""
    why = []
    boots = sorted(Path("/boot").glob("vmlinuz-*"), key=lambda p: _version_key(p.name[8:]), reverse=True)
    for vmlinuz in boots:
        ver = vmlinuz.name[len("vmlinuz-") :]
        moddir = Path("/lib/modules") / ver
        if not (moddir / "modules.dep").is_file():
            why.append(f"{vmlinuz}: no {moddir}/modules.dep")
            continue
        deps, builtin = _module_index(moddir)
        missing = [m for m in ("vcan", "can_raw", "9p", "9pnet_virtio") if m not in deps and m not in builtin]
        if missing:
            why.append(f"{vmlinuz}: kernel without modules {missing}")
            continue
        if not os.access(vmlinuz, os.R_OK):
            why.append(f"{vmlinuz}: not readable")
            continue
        return Kernel(ver, vmlinuz, moddir), ""
    if not boots:
        why.append("no /boot/vmlinuz-*")
    return None, "; ".join(why)


def _missing_tools() -> dict[str, str]:
    """{package: what is missing} for everything the VM needs that is not there."""
    missing = {}
    if find_qemu() is None:
        missing[APT_PACKAGES["qemu"]] = "qemu-system-x86_64"
    kernel, why = find_kernel()
    if kernel is None:
        missing[APT_PACKAGES["kernel"]] = f"a kernel with vcan/9p modules ({why})"
    if find_busybox() is None:
        missing[APT_PACKAGES["busybox"]] = "a static busybox"
    if find_can_utils() is None:
        missing[APT_PACKAGES["can-utils"]] = "candump/cansend/cangen"
    return missing


#: the make target that installs :data:`APT_PACKAGES` (the suite never installs anything)
INSTALL_TARGET = "make test-deps"


def ensure_tools() -> None:
    """Check that qemu, a CAN-capable kernel, static busybox and can-utils are there, or raise
    VMUnavailable naming the missing Debian packages and :data:`INSTALL_TARGET`."""
    missing = _missing_tools()
    if missing:
        what = "; ".join(f"{pkg} ({desc})" for pkg, desc in missing.items())
        raise VMUnavailable(f"missing {what}: install them with `sudo {INSTALL_TARGET}`")


# ---------------------------------------------------------------- initramfs


class _Cpio:
    """Minimal writer of a cpio 'newc' archive (what the kernel unpacks as initramfs)."""

    def __init__(self) -> None:
        self.buf = io.BytesIO()
        self.ino = 1

    def _entry(self, name: str, mode: int, data: bytes = b"", nlink: int = 1) -> None:
        nameb = name.encode() + b"\0"
        fields = [self.ino, mode, 0, 0, nlink, 0, len(data), 0, 0, 0, 0, len(nameb), 0]
        self.ino += 1
        hdr = b"070701" + b"".join(b"%08X" % f for f in fields)
        self.buf.write(hdr + nameb)
        self.buf.write(b"\0" * (-(len(hdr) + len(nameb)) % 4))
        self.buf.write(data)
        self.buf.write(b"\0" * (-len(data) % 4))

    def dir(self, name: str) -> None:
        self._entry(name, stat.S_IFDIR | 0o755, nlink=2)

    def file(self, name: str, data: bytes, mode: int = 0o644) -> None:
        self._entry(name, stat.S_IFREG | mode, data)

    def symlink(self, name: str, target: str) -> None:
        self._entry(name, stat.S_IFLNK | 0o777, target.encode())

    def finish(self) -> bytes:
        self._entry("TRAILER!!!", 0)
        return self.buf.getvalue()


def _read_module(path: Path) -> bytes:
    data = path.read_bytes()
    name = path.name
    if name.endswith(".ko.xz"):
        return lzma.decompress(data)
    if name.endswith(".ko.gz"):
        return gzip.decompress(data)
    if name.endswith(".ko.zst"):
        try:
            import zstandard

            return zstandard.ZstdDecompressor().decompressobj().decompress(data)
        except ImportError:
            pass
        zstd = shutil.which("zstd")
        if zstd is None:
            raise VMUnavailable(f"{path} is zstd-compressed and neither the zstd tool nor python zstandard is here")
        return subprocess.run([zstd, "-dc", str(path)], check=True, capture_output=True).stdout
    return data


def _module_load_list(kernel: Kernel) -> list[tuple[str, Path]]:
    """[(name, file)] in load order: MODULES plus their dependencies, built-ins skipped."""
    deps, builtin = _module_index(kernel.moddir)
    order: list[tuple[str, Path]] = []
    seen: set[str] = set()

    def add(name: str) -> None:
        key = name.replace("-", "_")
        if key in seen or key in builtin:
            return
        if key not in deps:
            raise VMUnavailable(f"kernel {kernel.version} has no module {name} (needed for the VM)")
        seen.add(key)
        rel, needs = deps[key]
        for dep_rel in reversed(needs):  # modules.dep lists the deepest dependency last
            add(re.sub(r"\.ko(\.(xz|zst|gz))?$", "", dep_rel.rsplit("/", 1)[-1]))
        order.append((key, kernel.moddir / rel))

    for m in MODULES:
        add(m)
    return order


_INIT = r"""#!/bin/busybox sh
# /init of the thermal_edge test VM (generated by tests/vm/vmrun.py).
/bin/busybox mkdir -p /proc /sys /dev /host /share /sbin /usr/bin /usr/sbin
/bin/busybox --install -s
export PATH=/bin:/sbin:/usr/bin:/usr/sbin
mount -t devtmpfs devtmpfs /dev 2>/dev/null
mount -t proc proc /proc
mount -t sysfs sysfs /sys
exec </dev/console >/dev/console 2>&1
say() { echo "@@VM:$*"; }
bye() { sync; poweroff -f; sleep 5; echo o > /proc/sysrq-trigger; }
fail() { say "ERROR $*"; bye; }
say INIT
for m in $(cat /modules/order); do
    insmod /modules/$m.ko || say "ERROR insmod $m"
done
mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=512000,cache=loose hostroot /host \
    || fail "mount of the host root over 9p failed"
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 vmshare /share \
    || fail "mount of the result share over 9p failed"
ip link add dev vcan0 type vcan || fail "ip link add dev vcan0 type vcan failed"
ip link set up vcan0 || fail "ip link set up vcan0 failed"
say "KERNEL $(uname -r)"
mount -t proc proc /host/proc || fail "mount proc in chroot"
mount -t sysfs sysfs /host/sys || fail "mount sysfs in chroot"
mount -t devtmpfs devtmpfs /host/dev || fail "mount devtmpfs in chroot"
mkdir -p /host/dev/pts /host/dev/shm
mount -t devpts devpts /host/dev/pts
mount -t tmpfs -o mode=1777 shm /host/dev/shm
# the guest gets a fresh /tmp; host directories under /tmp it needs (a checkout cloned there)
# are bound back in from the host root, read-only like the rest of it
mkdir -p /hosttmp
mount --bind /host/tmp /hosttmp || fail "bind mount of the host's /tmp"
mount -t tmpfs -o mode=1777 tmp /host/tmp || fail "mount tmpfs on /tmp in chroot"
if [ -f /share/tmpbinds ]; then
    while read -r p; do
        mkdir -p "/host$p" && mount --bind "/hosttmp${p#/tmp}" "/host$p" || say "ERROR bind of $p"
    done < /share/tmpbinds
fi
mount -t tmpfs -o mode=755 run /host/run 2>/dev/null
mkdir -p /host/tmp/vmshare /host/tmp/home
mount --bind /share /host/tmp/vmshare || fail "bind mount of the share"
# the host's iproute2 (run in the chroot: its symlinks are absolute) prints the vcan details
# (absolute path: busybox would run its own applet for a bare "ip")
HIP=$(chroot /host /bin/sh -c "command -v ip" 2>/dev/null)
case "$HIP" in /*) IP="chroot /host $HIP" ;; *) IP=ip ;; esac
say VCAN-BEGIN
$IP -details link show vcan0
say VCAN-END
say READY
chroot /host /bin/sh /tmp/vmshare/run.sh
say "STATUS $?"
sync
umount /host/tmp/vmshare 2>/dev/null
say DONE
bye
"""

_RUN_SH = """#!/bin/sh
# Generated by tests/vm/vmrun.py: runs inside the chroot of the guest.
cd {cwd} || {{ echo "vmrun: cannot cd to {cwd}" >{share}/stderr; echo 126 >{share}/status; exit 126; }}
mkdir -p {share}/artifacts
{exports}
mkdir -p "$HOME/.cache"
# seed matplotlib's font cache from the host's (building it under emulation costs ~10 s)
MPL_SRC={mpl_cache}
if [ -n "$MPL_SRC" ] && [ -d "$MPL_SRC" ]; then cp -r "$MPL_SRC" "$MPLCONFIGDIR" 2>/dev/null; fi
( {cmd}
) <{share}/stdin >{share}/stdout 2>{share}/stderr
rc=$?
echo $rc >{share}/status
exit $rc
"""


def _host_mpl_cache() -> str:
    """The host's matplotlib cache dir if it holds a font list (copied into the guest's HOME), else ""."""
    for cand in (
        os.environ.get("MPLCONFIGDIR"),
        os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "matplotlib"),
    ):
        if cand and any(Path(cand).glob("fontlist-*.json")):
            return str(Path(cand).resolve())
    return ""


def _warm_host_mpl_cache(python: str = DEFAULT_PYTHON) -> None:
    """Build matplotlib's font cache on the host (fast here), if that python has matplotlib."""
    if _host_mpl_cache() or not os.access(python, os.X_OK):
        return
    code = (
        "import importlib.util\n"
        "if importlib.util.find_spec('matplotlib'):\n"
        "    import matplotlib.font_manager\n"
    )
    try:
        subprocess.run([python, "-c", code], capture_output=True, timeout=180, check=False)
    except (OSError, subprocess.SubprocessError):
        pass


def _cache_dir() -> Path:
    base = os.environ.get("THERMAL_EDGE_VM_CACHE")
    path = Path(base) if base else Path(tempfile.gettempdir()) / "thermal_edge-vm-cache"
    path.mkdir(parents=True, exist_ok=True)
    return path


def build_initramfs(kernel: Kernel, busybox: Path, cache_dir: Path | None = None) -> Path:
    """The gzip'd cpio initramfs for ``kernel``, from the cache when its content key matches."""
    cache_dir = cache_dir or _cache_dir()
    mods = _module_load_list(kernel)
    key = hashlib.sha256()
    key.update(_INIT.encode())
    key.update(hashlib.sha256(busybox.read_bytes()).digest())
    for name, path in mods:
        st = path.stat()
        key.update(f"{name}:{path}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    out = cache_dir / f"initramfs-{kernel.version}-{key.hexdigest()[:16]}.cpio.gz"
    if out.is_file() and out.stat().st_size > 0:
        return out
    cpio = _Cpio()
    for d in ("bin", "dev", "proc", "sys", "host", "share", "modules", "sbin", "usr", "usr/bin", "usr/sbin", "tmp"):
        cpio.dir(d)
    cpio.file("bin/busybox", busybox.read_bytes(), 0o755)
    cpio.symlink("bin/sh", "busybox")
    cpio.file("init", _INIT.encode(), 0o755)
    for name, path in mods:
        cpio.file(f"modules/{name}.ko", _read_module(path))
    cpio.file("modules/order", ("\n".join(n for n, _ in mods) + "\n").encode())
    data = gzip.compress(cpio.finish(), compresslevel=6)
    tmp = out.with_suffix(f".tmp{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, out)
    return out


# ---------------------------------------------------------------- the VM


@contextlib.contextmanager
def _one_vm_at_a_time():
    """Hold the host-wide boot lock (a file in the VM cache) while a VM runs.

    Two suites side by side would otherwise emulate two guests at once on two cores: each guest's
    real-time service (TE_Limits every 100 ms) then stalls for seconds under TCG. The second
    boot waits for the first to power off instead.
    """
    with open(_cache_dir() / "boot.lock", "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _kvm_usable() -> tuple[bool, str]:
    if not os.path.exists("/dev/kvm"):
        return False, "no /dev/kvm"
    if not os.access("/dev/kvm", os.R_OK | os.W_OK):
        return False, "/dev/kvm not accessible"
    return True, ""


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return "unknown"


class VM:
    """A qemu VM with SocketCAN; each :meth:`run` boots it afresh, runs one command, powers it off."""

    def __init__(
        self,
        *,
        memory_mb: int | None = None,
        smp: int | None = None,
        accel: str | None = None,
        cache_dir: str | os.PathLike | None = None,
        verbose: bool | None = None,
    ) -> None:
        self.memory_mb = int(memory_mb or os.environ.get("THERMAL_EDGE_VM_MEM", 1536))
        self.smp = int(smp or os.environ.get("THERMAL_EDGE_VM_SMP") or min(2, os.cpu_count() or 1))
        self.accel_request = (accel or os.environ.get("THERMAL_EDGE_VM_ACCEL") or "auto").lower()
        self.cache_dir = Path(cache_dir) if cache_dir else None
        self.verbose = verbose if verbose is not None else os.environ.get("THERMAL_EDGE_VM_VERBOSE") == "1"
        self.kernel: Kernel | None = None
        self.qemu: Path | None = None
        self.initramfs: Path | None = None
        #: "kvm" or "tcg" once prepared.
        self.accel: str = ""
        #: Why KVM is not used (empty when it is).
        self.kvm_note: str = ""
        #: The first successful boot of :meth:`prepare` (the smoke run).
        self.first_result: Result | None = None
        self.prepare_seconds: float | None = None
        self.runs: list[Result] = []
        #: The KVM probe boot, when one was made.
        self.kvm_probe: Result | None = None

    # -- setup

    def prepare(self) -> VM:
        """Find everything, build the initramfs, pick KVM or TCG and boot once; or raise VMUnavailable."""
        if self.accel_request not in ("auto", "kvm", "tcg"):
            raise ValueError(f"accel must be auto, kvm or tcg, not {self.accel_request!r}")
        if os.environ.get("THERMAL_EDGE_VM", "").lower() in ("0", "no", "off", "false"):
            raise VMUnavailable("disabled by THERMAL_EDGE_VM=0")
        if sys.platform != "linux":
            raise VMUnavailable(f"needs a Linux host, this is {sys.platform}")
        t0 = time.monotonic()
        ensure_tools()
        self.qemu = find_qemu()
        kernel, why = find_kernel()
        if kernel is None:
            raise VMUnavailable(f"kernel without vcan: {why}")
        self.kernel = kernel
        busybox = find_busybox()
        assert busybox is not None and self.qemu is not None
        self.cache_dir = self.cache_dir or _cache_dir()
        self.initramfs = build_initramfs(kernel, busybox, self.cache_dir)
        self._choose_accel()
        _warm_host_mpl_cache()
        smoke = self.run("true", timeout=120)
        if not smoke.ok:
            raise VMUnavailable(f"boot failed ({self.accel}):\n{smoke.describe()}")
        self.first_result = smoke
        self.prepare_seconds = time.monotonic() - t0
        _log(
            f"VM ready: kernel {smoke.kernel} ({kernel.vmlinuz}), accel {self.accel}"
            + (f" ({self.kvm_note})" if self.kvm_note else "")
            + f", vcan0 up, boot {_fmt_s(smoke.boot_seconds)}, boot+poweroff {smoke.wall_seconds:.1f} s"
        )
        return self

    def _choose_accel(self) -> None:
        if self.accel_request == "tcg":
            self.accel, self.kvm_note = "tcg", "TCG requested"
            return
        usable, why = _kvm_usable()
        if not usable:
            if self.accel_request == "kvm":
                raise VMUnavailable(f"KVM requested but {why}")
            self.accel, self.kvm_note = "tcg", why
            return
        # A KVM that hangs or aborts has been seen on these machines: probe it with
        # a real short boot, and remember the verdict for this host boot.
        assert self.cache_dir is not None
        verdict_file = self.cache_dir / f"kvm-probe-{_boot_id()}-{self.kernel.version}"
        if verdict_file.is_file() and self.accel_request == "auto":
            verdict = verdict_file.read_text().strip()
            if verdict == "kvm":
                self.accel, self.kvm_note = "kvm", ""
            else:
                self.accel, self.kvm_note = "tcg", f"KVM failed its probe earlier on this host boot: {verdict}"
            return
        self.accel = "kvm"
        probe = self.run("true", timeout=15)
        self.runs.remove(probe)
        self.kvm_probe = probe
        if probe.ok:
            verdict_file.write_text("kvm\n")
            self.kvm_note = ""
            return
        reason = "timed out" if probe.timed_out else f"exit {probe.returncode}"
        errs = "; ".join(probe.errors)[:200]
        tail = " | ".join(probe.console.strip().splitlines()[-3:])[:300] or "no console output"
        note = f"KVM probe boot {reason} after {probe.wall_seconds:.1f} s ({errs or tail})"
        if self.accel_request == "kvm":
            raise VMUnavailable(note)
        verdict_file.write_text(note + "\n")
        self.accel, self.kvm_note = "tcg", note
        _log(note + "; falling back to TCG")

    # -- running

    def _qemu_argv(self, share: Path) -> list[str]:
        assert self.qemu and self.kernel and self.initramfs
        argv = [str(self.qemu), "-nodefaults", "-no-user-config", "-machine", "q35"]
        if self.accel == "kvm":
            argv += ["-accel", "kvm", "-cpu", "host"]
        else:
            argv += ["-accel", "tcg", "-cpu", "max"]
        argv += [
            "-smp", str(self.smp),
            "-m", str(self.memory_mb),
            "-kernel", str(self.kernel.vmlinuz),
            "-initrd", str(self.initramfs),
            "-append", "console=ttyS0 panic=-1 oops=panic quiet loglevel=3 rdinit=/init mitigations=off",
            "-display", "none",
            "-serial", "stdio",
            "-monitor", "none",
            "-no-reboot",
            "-virtfs", "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap",
            "-virtfs", f"local,path={share},mount_tag=vmshare,security_model=none",
        ]  # fmt: skip
        return argv

    def run(
        self,
        cmd: str,
        timeout: float = 120.0,
        *,
        cwd: str = DEFAULT_CWD,
        env: dict[str, str] | None = None,
        stdin: str | bytes = b"",
        files: dict[str, str | bytes] | None = None,
    ) -> Result:
        """Boot, run the shell command line ``cmd`` in ``cwd`` in the guest, power off.

        ``timeout`` is the hard limit for the whole boot-run-poweroff in seconds;
        qemu is killed when it expires (``Result.timed_out``, ``returncode`` None).
        ``files`` are put into the share before boot and are visible in the guest
        at ``$VM_SHARE/files/<name>``.  Never raises for a failing command: look
        at the Result (``check()`` raises with the whole report).
        """
        if self.initramfs is None or not self.accel:
            raise RuntimeError("call prepare() first")
        with tempfile.TemporaryDirectory(prefix="thermal_edge-vm-") as tmp:
            share = Path(tmp)
            os.chmod(share, 0o777)
            exports = {
                "PATH": "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
                "HOME": "/tmp/home",
                "TMPDIR": "/tmp",
                "LANG": "C.UTF-8",
                "PYTHONDONTWRITEBYTECODE": "1",
                "PYTHONUNBUFFERED": "1",
                "THERMAL_EDGE_IN_VM": "1",
                "VM_SHARE": GUEST_SHARE,
                "VM_ARTIFACTS": f"{GUEST_SHARE}/artifacts",
                "VM_FILES": f"{GUEST_SHARE}/files",
            }
            mpl_cache = _host_mpl_cache()
            exports["MPLCONFIGDIR"] = "/tmp/home/.cache/matplotlib"
            exports["MPLBACKEND"] = "Agg"
            if "CI" in os.environ:
                exports["CI"] = os.environ["CI"]
            exports.update(env or {})
            export_lines = "\n".join(f"export {k}={shlex.quote(v)}" for k, v in exports.items())
            (share / "run.sh").write_text(
                _RUN_SH.format(
                    cwd=shlex.quote(cwd), share=GUEST_SHARE, exports=export_lines, cmd=cmd, mpl_cache=shlex.quote(mpl_cache)
                )
            )
            (share / "stdin").write_bytes(stdin.encode() if isinstance(stdin, str) else stdin)
            under_tmp = sorted({str(Path(d).resolve()) for d in (cwd, Path(__file__).resolve().parents[2])
                                if Path(d).resolve().is_relative_to("/tmp")})
            if under_tmp:
                (share / "tmpbinds").write_text("".join(f"{d}\n" for d in under_tmp))
            if files:
                (share / "files").mkdir()
                for name, content in files.items():
                    dest = share / "files" / name
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    dest.write_bytes(content.encode() if isinstance(content, str) else content)
            with _one_vm_at_a_time():
                result = self._boot(cmd, share, timeout)
        self.runs.append(result)
        return result

    def _boot(self, cmd: str, share: Path, timeout: float) -> Result:
        argv = self._qemu_argv(share)
        if os.geteuid() == 0 and shutil.which("nice"):
            # The guest runs the service in real time (TE_Limits every 100 ms, the inverter's 300 ms
            # timeout) on an emulated CPU: it gets the host's CPU before the suite's other worker
            # and a second suite beside it, whose tests are paced and wait for their service.
            argv = ["nice", "-n", str(QEMU_NICE), *argv]
        console: list[str] = []
        marks: dict[str, float] = {}
        t0 = time.monotonic()
        proc = subprocess.Popen(
            argv,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

        def reader() -> None:
            assert proc.stdout is not None
            for raw in iter(proc.stdout.readline, b""):
                line = raw.decode("utf-8", "replace").rstrip("\r\n")
                console.append(line)
                if self.verbose:
                    print(f"[vm console] {line}", file=sys.stderr, flush=True)
                if line.startswith(MARK):
                    word = line[len(MARK) :].split(" ", 1)[0]
                    marks.setdefault(word, time.monotonic() - t0)

        thread = threading.Thread(target=reader, daemon=True)
        thread.start()
        timed_out = False
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
            _kill(proc)
        except BaseException:  # KeyboardInterrupt etc.: never leave qemu behind
            _kill(proc)
            raise
        wall = time.monotonic() - t0
        thread.join(timeout=5)
        text = "\n".join(console)

        def read(name: str) -> str:
            try:
                return (share / name).read_text(errors="replace")
            except OSError:
                return ""

        status = read("status").strip()
        returncode = int(status) if status.lstrip("-").isdigit() else None
        m = re.search(r"^@@VM:KERNEL (\S+)", text, re.M)
        kernel = m.group(1) if m else ""
        vm = re.search(r"^@@VM:VCAN-BEGIN\n(.*?)^@@VM:VCAN-END", text, re.M | re.S)
        vcan = vm.group(1).strip() if vm else ""
        errors = re.findall(r"^@@VM:ERROR (.*)$", text, re.M)
        if proc.returncode not in (0, None) and not timed_out and returncode is None:
            errors.append(f"qemu exited with status {proc.returncode}")
        artifacts: dict[str, bytes] = {}
        adir = share / "artifacts"
        if adir.is_dir():
            for p in sorted(adir.rglob("*")):
                if p.is_file():
                    artifacts[str(p.relative_to(adir))] = p.read_bytes()
        ready, done = marks.get("READY"), marks.get("STATUS")
        return Result(
            cmd=cmd,
            returncode=returncode,
            stdout=read("stdout"),
            stderr=read("stderr"),
            kernel=kernel,
            vcan=vcan,
            console=text,
            accel=self.accel,
            boot_seconds=ready,
            cmd_seconds=(done - ready) if (ready is not None and done is not None) else None,
            wall_seconds=wall,
            timed_out=timed_out,
            artifacts=artifacts,
            errors=errors,
        )

    # -- conveniences

    def python(
        self, code: str, timeout: float = 120.0, *, args: str = "", python: str = DEFAULT_PYTHON, **kw
    ) -> Result:
        """Run a Python script (source text) with the project's venv interpreter in the guest.

        ``args`` is appended to the command line as is (shell words: quote them).
        """
        files = dict(kw.pop("files", None) or {})
        files["_script.py"] = code
        return self.run(f"{shlex.quote(python)} {GUEST_SHARE}/files/_script.py {args}", timeout, files=files, **kw)

    def pytest(
        self, args: str, timeout: float = 300.0, *, python: str = DEFAULT_PYTHON, cwd: str = DEFAULT_CWD, **kw
    ) -> Result:
        """Run ``python -m pytest <args>`` (a shell-word string) in the guest; the exit status is pytest's.

        The cache provider is off (the host tree is read-only in the guest) and
        tests see ``THERMAL_EDGE_IN_VM=1``.  ``-p no:cacheprovider -q`` come first,
        so ``args`` may add to or override them.
        """
        return self.run(
            f"{shlex.quote(python)} -m pytest -p no:cacheprovider -q {args}", timeout, cwd=cwd, **kw
        )

    def summary(self) -> str:
        """One line on the VM for logs: kernel, accel, boot and per-run times."""
        if not self.runs:
            return "VM not booted"
        boots = [r.boot_seconds for r in self.runs if r.boot_seconds is not None]
        k = next((r.kernel for r in self.runs if r.kernel), "?")
        return (
            f"kernel {k}, accel {self.accel}" + (f" ({self.kvm_note})" if self.kvm_note else "")
            + f", {len(self.runs)} boots, boot-to-ready "
            + (f"{min(boots):.1f}-{max(boots):.1f} s" if boots else "?")
            + ", runs: "
            + ", ".join(f"{r.wall_seconds:.1f} s" for r in self.runs)
        )


def _kill(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        proc.kill()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        pass


# ---------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="vmrun.py",
        description="Run a shell command in a qemu VM with SocketCAN (vcan0 up) and the host root read-only.",
    )
    parser.add_argument("--timeout", type=float, default=300.0, help="hard limit for boot+run+poweroff, s")
    parser.add_argument("--cwd", default=DEFAULT_CWD, help="working directory in the guest")
    parser.add_argument("--accel", choices=("auto", "kvm", "tcg"), default=None)
    parser.add_argument("--mem", type=int, default=None, help="guest memory, MiB")
    parser.add_argument("-v", "--verbose", action="store_true", help="echo the guest console")
    parser.add_argument("cmd", nargs=argparse.REMAINDER, help="-- CMD... (joined into a shell command line)")
    ns = parser.parse_args(argv)
    words = ns.cmd[1:] if ns.cmd[:1] == ["--"] else ns.cmd
    if not words:
        parser.error("no command given: vmrun.py -- CMD...")
    cmd = words[0] if len(words) == 1 else " ".join(shlex.quote(w) for w in words)
    vm = VM(accel=ns.accel, memory_mb=ns.mem, verbose=ns.verbose)
    try:
        vm.prepare()
    except VMUnavailable as exc:
        print(f"vmrun: VM unavailable: {exc}", file=sys.stderr)
        return 77
    res = vm.run(cmd, timeout=ns.timeout, cwd=ns.cwd)
    sys.stdout.write(res.stdout)
    sys.stderr.write(res.stderr)
    print(
        f"[vm] kernel {res.kernel}, accel {res.accel}, vcan0: {res.vcan.splitlines()[0] if res.vcan else '?'}\n"
        f"[vm] boot {_fmt_s(res.boot_seconds)}, command {_fmt_s(res.cmd_seconds)}, wall {res.wall_seconds:.1f} s, "
        + ("TIMED OUT" if res.timed_out else f"exit {res.returncode}"),
        file=sys.stderr,
    )
    if res.returncode is None:
        print(res.describe(), file=sys.stderr)
        return 124 if res.timed_out else 125
    return res.returncode


if __name__ == "__main__":
    sys.exit(main())
