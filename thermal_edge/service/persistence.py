"""Persistence of parameters, their history and the thermal state.

One JSON file, ``state.json`` in the state directory, written atomically: a temporary file
``state.json.tmp-<pid>`` in the same directory, ``fsync``, ``rename`` over the old file,
``fsync`` of the directory. A reader therefore sees the old or the new file, never a torn one,
even after a power cut; a temporary file left by a kill during a save is removed at the next start.

Loading is bounded and total: whatever is at the path (a directory, a FIFO, a 256 MiB file, 100,000
nested brackets, a 5,000-digit number, binary, another program's JSON, wrong types anywhere), the
result is a validated :class:`PersistedState` or None -- never an exception. The file is ``stat``-ed
first and never read beyond :data:`MAX_BYTES`; the JSON is parsed only after a bracket-depth scan
(:data:`MAX_DEPTH`) and with hooks that refuse numbers longer than :data:`MAX_NUMBER_CHARS`
characters and ``NaN``/``Infinity``; then every field is type-checked into the dataclass. An
unusable file is logged with its name and the reason, counted (:attr:`StateStore.load_errors`),
moved aside to ``state.json.corrupt-<time>-<pid>`` (the newest :data:`KEEP_CORRUPT` are kept for
forensics) and the service starts from the defaults. Two exceptions: a learned parameter the model
no longer has (renamed or removed by a model update), or whose value in the model is not the one it
was learned from (a new model file, a calibrated value in ``edge.yaml``), is dropped with a WARNING
naming it and counted (:attr:`StateStore.params_dropped`); the other learned parameters are kept.

A state directory that cannot be written (read-only, full, not creatable) is not a reason to stop
protecting: :meth:`StateStore.probe` says so at start, every save retries, and failed saves are
logged on the first, second, fourth, ... (:func:`_worth_logging`) with their count, and once more
when a save works again.

Saved state is loadable by construction: :meth:`StateStore.save` encodes the state and runs the
very same :func:`decode` on the bytes it is about to write; a state that would not load is refused
(logged, counted, the previous file kept). Parameter values within a relative
:data:`~thermal_edge.lptn.model.BOUND_ROUNDOFF_REL` of a bound (round-off of an adaptation that
reached it) are set onto the bound, on save and on load alike.

On start the saved thermal state is **cooled over the downtime** with the model
(:func:`thermal_edge.lptn.cool_down`: the machine at rest, one zero-order-hold step, exact for held
inputs), then corrected by the first measurements through the observer
(:meth:`.estimate.StateEstimate.start`).
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import stat
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ThermalEdgeError
from ..lptn import Model, ParameterError
from ..lptn.vocabulary import TEMPERATURE

__all__ = ["PersistedState", "StateError", "StateStore", "decode"]

log = logging.getLogger(__name__)

FORMAT = "thermal_edge.state"
VERSION = 1
#: a learned parameter's model value is the one it was saved with within this relative difference
#: (a value written to YAML and read back, not a new calibration)
NOMINAL_REL = 1e-9
FILENAME = "state.json"
#: Largest state file read, bytes. A full one (500 decisions, a 40-node covariance) is < 1 MiB;
#: refusing a larger one costs at most about five times this in memory, beyond it nothing.
MAX_BYTES = 8 * 1024 * 1024
#: Deepest nesting of arrays/objects accepted (the format needs 4: state -> decisions -> decision -> params).
MAX_DEPTH = 16
#: Most values (numbers, strings, ...) accepted: bounds the memory of the parsed document
#: (a full file holds ~20,000).
MAX_VALUES = 250_000
#: Longest number literal accepted, characters (``repr`` of a float is at most 24).
MAX_NUMBER_CHARS = 40
#: Corrupt files kept (moved aside) for forensics; older ones are deleted.
KEEP_CORRUPT = 3

_CORRUPT_PREFIX = f"{FILENAME}.corrupt-"
# what a save in progress leaves when killed: this module's temporary name and the earlier ``.state.json.<pid>.tmp``
_TEMP_RE = re.compile(rf"^(?:{re.escape(FILENAME)}\.tmp.*|\.{re.escape(FILENAME)}\.\d+\.tmp)$")
_QUOTE, _OPEN, _CLOSE, _SEPARATORS = ord('"'), b"[{", b"]}", b",:"


class StateError(ThermalEdgeError, ValueError):
    """A state file that cannot be used (the message says why)."""


def _worth_logging(n: int) -> bool:
    """Log the ``n``-th failure in a row? The 1st, 2nd, 4th, ... 64th, then every 64th: a state
    directory that stays unwritable stays visible (about hourly at the 60 s save interval) without
    a line a minute."""
    return n & (n - 1) == 0 if n <= 64 else n % 64 == 0


# ------------------------------------------------------------------------------------------
# bounded parsing
def _structure(data: bytes) -> tuple[int, int]:
    """Deepest ``[``/``{`` nesting and number of values of a JSON text, without parsing it.

    Escaped backslashes and quotes are removed (``bytes.replace``, in C), then one vectorised pass
    in 1 MiB chunks marks what lies inside strings (parity of the quotes so far) and sums the
    brackets and separators outside them: no recursion, and the memory stays one copy of the
    file plus a few chunk-sized arrays whatever the file holds.
    """
    plain = data.replace(b"\\\\", b"").replace(b'\\"', b"")
    depth = deepest = values = quotes_so_far = 0
    chunk = 1 << 20
    for k in range(0, len(plain), chunk):
        b = np.frombuffer(plain, dtype=np.uint8, count=min(chunk, len(plain) - k), offset=k)
        quotes = np.cumsum(b == _QUOTE, dtype=np.int64) + quotes_so_far
        quotes_so_far = int(quotes[-1])
        outside = (quotes & 1) == 0
        opens = outside & ((b == _OPEN[0]) | (b == _OPEN[1]))
        closes = outside & ((b == _CLOSE[0]) | (b == _CLOSE[1]))
        run = np.cumsum(opens.astype(np.int64) - closes, dtype=np.int64) + depth
        deepest = max(deepest, int(run.max()))
        depth = int(run[-1])
        values += int(np.count_nonzero(outside & ((b == _SEPARATORS[0]) | (b == _SEPARATORS[1]))))
    return deepest, values + 1


def _parse_int(text: str) -> int:
    if len(text) > MAX_NUMBER_CHARS:
        raise StateError(f"a number of {len(text)} digits")
    return int(text)


def _parse_float(text: str) -> float:
    if len(text) > MAX_NUMBER_CHARS:
        raise StateError(f"a number of {len(text)} characters")
    v = float(text)
    if not math.isfinite(v):
        raise StateError(f"a number out of range ({text[:20]})")
    return v


def _parse_constant(text: str) -> Any:
    raise StateError(f"{text} is not a number")


def decode(data: bytes, model: Model, dropped: list[str] | None = None,
           outdated: list[tuple[str, float, float, float]] | None = None) -> PersistedState:
    """Bytes of a state file -> a validated state for ``model``; the one check of load and save.

    Parameters
    ----------
    data : bytes
    model : Model
    dropped : list of str, optional
        Given (on load): parameter names the model does not have are dropped and appended here.
        None (on save): such a name makes the state unusable, so a saved file never holds one.
    outdated : list, optional
        Given (on load): learned parameters whose model value changed since they were saved are
        dropped and appended here (:meth:`PersistedState.from_json`).

    Raises
    ------
    StateError
        Anything that makes the bytes unusable (the message says what, for a log line).
    """
    if len(data) > MAX_BYTES:
        raise StateError(f"larger than {MAX_BYTES // (1024 * 1024)} MiB")
    if not data.strip():
        raise StateError("empty file")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise StateError(f"not UTF-8 text (byte {exc.start})") from None
    depth, values = _structure(data)
    if depth > MAX_DEPTH:
        raise StateError(f"nested {depth} deep (at most {MAX_DEPTH})")
    if values > MAX_VALUES:
        raise StateError(f"about {values} values (at most {MAX_VALUES})")
    try:
        raw = json.loads(text, parse_int=_parse_int, parse_float=_parse_float, parse_constant=_parse_constant)
    except json.JSONDecodeError as exc:
        raise StateError(f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except (RecursionError, MemoryError, ValueError) as exc:  # StateError from the hooks included
        raise StateError(f"not usable JSON: {exc}") from None
    return PersistedState.from_json(raw, model, dropped, outdated)


# ------------------------------------------------------------------------------------------
# typed fields
def _short(v: Any) -> str:
    """``repr`` of a value from the file, cut for a log line (the value may be megabytes)."""
    if isinstance(v, (dict, list)):
        return f"a JSON {'object' if isinstance(v, dict) else 'list'}"
    r = repr(v[:40] if isinstance(v, str) else v)
    return r if len(r) <= 40 else r[:37] + "..."


def _number(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise StateError(f"{what}: expected a number, got {type(v).__name__}")
    x = float(v)
    if not math.isfinite(x):
        raise StateError(f"{what}: not finite")
    return x


def _count(v: Any, what: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise StateError(f"{what}: expected a non-negative integer, got {_short(v)}")
    return int(v)


def _list(v: Any, what: str, item: Callable[[Any, str], Any]) -> list[Any]:
    if not isinstance(v, list):
        raise StateError(f"{what}: expected a list, got {type(v).__name__}")
    return [item(x, f"{what}[{i}]") for i, x in enumerate(v)]


def _mapping(v: Any, what: str, item: Callable[[Any, str], Any]) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise StateError(f"{what}: expected an object, got {type(v).__name__}")
    return {k: item(x, f"{what}.{k}") for k, x in v.items()}


def _string(v: Any, what: str) -> str:
    if not isinstance(v, str):
        raise StateError(f"{what}: expected a string, got {type(v).__name__}")
    return v


def _decision(v: Any, what: str) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise StateError(f"{what}: expected an object, got {type(v).__name__}")
    return dict(v)  # its values are whatever the adapter recorded (JSON, depth-bounded by the parser)


#: a state saved this far in the future by this host's clock is announced as such (clocks of two
#: hosts, or of one host across an NTP step, differ by seconds), s
FUTURE_TOLERANCE_S = 60.0


@dataclass
class PersistedState:
    """What survives a restart."""

    model: str
    saved_at: float  # clock time of the state, s since the epoch
    parameters: dict[str, float]  # every parameter that differs from the model file is kept here
    param_version: int = 0
    adapt_runs: int = 0
    decisions: list[dict[str, Any]] = field(default_factory=list)
    nodes: list[str] = field(default_factory=list)
    T: list[float] = field(default_factory=list)  # best estimate, degC
    sigma: list[float] = field(default_factory=list)  # its standard deviation, K
    T_pred: list[float] = field(default_factory=list)  # open-loop prediction, degC
    #: the commissioned prediction (the model file's parameters on open loop), degC
    T_commissioned: list[float] = field(default_factory=list)
    P: list[list[float]] = field(default_factory=list)  # covariance of the estimate, K²
    inputs: dict[str, float] = field(default_factory=dict)  # last inputs (ambient for the cool-down)
    saved_wall: float = 0.0
    #: the model's own value (its file's, with edge.yaml's model.parameters) of each learned parameter
    #: when saved: a learned value is kept only while the model still starts that parameter there
    nominal: dict[str, float] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, **self.__dict__}

    @classmethod
    def from_json(cls, raw: Any, model: Model, dropped: list[str] | None = None,
                  outdated: list[tuple[str, float, float, float]] | None = None) -> PersistedState:
        """Validate a parsed state file into a state for ``model``.

        Every field is type-checked; parameters are checked against the model's bounds after
        round-off at a bound is set onto it (:meth:`Model.snap_to_bounds`). With ``dropped`` given,
        parameter names the model does not have are removed and appended to it (a model update
        that renames one parameter must not cost the others); without, they are an error. With
        ``outdated`` given, a learned parameter whose value in the model differs from the one
        saved with it (a new model file, a calibrated value in edge.yaml) is removed and appended
        as (name, saved model value, model value now, learned value): it was learned from another
        sta

        Raises
        ------
        StateError
            The first problem found.
        """
        if not isinstance(raw, dict):
            raise StateError(f"not a state file: a JSON {type(raw).__name__}, not an object")
        if raw.get("format") != FORMAT:
            raise StateError(f"not a state file: format is {_short(raw.get('format'))}, expected {FORMAT!r}")
        if raw.get("version") != VERSION:
            raise StateError(f"version {_short(raw.get('version'))} is not supported (expected {VERSION})")
        if raw.get("model") != model.name:
            raise StateError(f"it belongs to model {_short(raw.get('model'))}, the service runs {model.name!r}")
        known = {f.name for f in fields(cls)} | {"format", "version"}
        extra = sorted(set(raw) - known)
        if extra:
            raise StateError(f"unknown field {_short(extra[0])}")
        for k in ("saved_at", "parameters"):
            if k not in raw:
                raise StateError(f"missing field {k!r}")
        params = _mapping(raw["parameters"], "parameters", _number)
        nominal = _mapping(raw.get("nominal", {}), "nominal", _number)
        if dropped is not None:
            names = {p.name for p in model.parameters}
            dropped.extend(sorted(k for k in params if k not in names))
            params = {k: v for k, v in params.items() if k in names}
        if outdated is not None:
            now = dict(zip(model.parameter_names, model.nominal()))
            for k in sorted(params):
                if k in nominal and not math.isclose(nominal[k], now[k], rel_tol=NOMINAL_REL, abs_tol=0.0):
                    outdated.append((k, nominal[k], float(now[k]), params.pop(k)))
        try:
            params = model.snap_to_bounds(params)
            model.check_parameters(params)
        except ParameterError as exc:
            raise StateError(str(exc)) from None
        st = cls(
            model=model.name,
            saved_at=_number(raw["saved_at"], "saved_at"),
            parameters=params,
            param_version=_count(raw.get("param_version", 0), "param_version"),
            adapt_runs=_count(raw.get("adapt_runs", 0), "adapt_runs"),
            decisions=_list(raw.get("decisions", []), "decisions", _decision),
            nodes=_list(raw.get("nodes", []), "nodes", _string),
            T=_list(raw.get("T", []), "T", _number),
            sigma=_list(raw.get("sigma", []), "sigma", _number),
            T_pred=_list(raw.get("T_pred", []), "T_pred", _number),
            T_commissioned=_list(raw.get("T_commissioned", []), "T_commissioned", _number),
            P=_list(raw.get("P", []), "P", lambda row, w: _list(row, w, _number)),
            inputs=_mapping(raw.get("inputs", {}), "inputs", _number),
            saved_wall=_number(raw.get("saved_wall", 0.0), "saved_wall"),
            nominal={k: v for k, v in nominal.items() if k in params},
        )
        n = len(model.nodes)
        if st.T or st.sigma or st.T_pred or st.T_commissioned or st.P or st.nodes:
            if st.nodes != list(model.nodes):
                raise StateError("its node list differs from the model's")
            if len(st.T) != n:
                raise StateError(f"T has {len(st.T)} values for {n} nodes")
            for arr, what in ((st.sigma, "sigma"), (st.T_pred, "T_pred"), (st.T_commissioned, "T_commissioned")):
                if arr and len(arr) != n:
                    raise StateError(f"{what} has {len(arr)} values for {n} nodes")
            if any(x < 0 for x in st.sigma):
                raise StateError("sigma has a negative value")
            if st.P and (len(st.P) != n or any(len(r) != n for r in st.P)):
                raise StateError(f"P is not {n} x {n}")
            if st.P and any(st.P[i][i] <= 0 for i in range(n)):
                # the observer adds process noise every tick: no saved estimate is exact, and a zero
                # variance would keep readings from ever correcting the node
                raise StateError("P has a variance of zero or less (no estimate is exact)")
            for arr, what in ((st.T, "T"), (st.T_pred, "T_pred"), (st.T_commissioned, "T_commissioned")):
                found = TEMPERATURE.series_problem(np.asarray(arr, dtype=float)) if arr else None
                if found is not None:
                    at, cause = found
                    where = what if at is None else f"{what}[{at}] (node {model.nodes[at]!r})"
                    raise StateError(f"{where}: temperatures outside {TEMPERATURE.lo:g}..{TEMPERATURE.hi:g} degC: {cause}")
        for name, v in st.inputs.items():
            role = model.input_roles.get(name)
            problem = role.plausible.problem(v) if role is not None else None
            if problem:
                raise StateError(f"inputs.{name}: {problem}")
        return st


# ------------------------------------------------------------------------------------------
LOCKNAME = "lock"


class StateDirInUse(ThermalEdgeError):
    """Another process holds the state directory: two services would overwrite each other's
    learned parameters and thermal state."""


def _kind(mode: int) -> str:
    """What a file of this ``st_mode`` is, for a message."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


class StateLock:
    """An exclusive advisory lock (``flock``) on ``<state dir>/lock`` while a service runs.

    The kernel releases it when the process ends, however it ends, so a killed service never
    leaves a stale lock. Within one process the lock is shared (counted): the process is one
    service. A directory that cannot be written is not locked (the store logs that it cannot
    save; the service protects without persistence). A lock path that is not a regular file (a
    directory, a FIFO, a symbolic link) or a filesystem without locks is not locked either, with
    a WARNING naming the path: the service must protect whatever is in its state directory. The
    pid written into the lock file only names the holder for the message of a second service; a
    full disk that refuses it leaves the lock held.
    """

    #: per lock file of this process: [file descriptor, holders]
    _held: dict[Path, list[int]] = {}

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.path = Path(os.path.abspath(Path(directory) / LOCKNAME))
        self.held = False

    def acquire(self) -> bool:
        """Take the lock: True when held, False when the directory cannot hold a lock file.

        Raises
        ------
        StateDirInUse
            Another process holds it (the message names the directory and that process's pid).
        """
        import fcntl  # POSIX only, as the service

        if self.held:
            return True
        if (entry := StateLock._held.get(self.path)) is not None:
            entry[1] += 1
            self.held = True
            return True
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            mode = os.lstat(self.path).st_mode if os.path.lexists(self.path) else stat.S_IFREG
        except OSError:
            return False  # the store says that it cannot save
        if not stat.S_ISREG(mode):
            return self._unlocked(f"it is {_kind(mode)}, not a lock file (remove it)")
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError:
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise StateDirInUse(f"state.dir {self.path.parent}: in use by another thermal-edge (pid {holder}); two "
                                "services on one state directory would overwrite each other's learned state") from None
        except OSError as exc:  # a filesystem without locks
            os.close(fd)
            return self._unlocked(f"the filesystem refuses locks ({exc.strerror or exc})")
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:  # a full disk: the lock is held all the same, only the holder's pid is not named
            pass
        StateLock._held[self.path] = [fd, 1]
        self.held = True
        return True

    def _unlocked(self, why: str) -> bool:
        log.warning("cannot lock the state directory through %s: %s; the service runs without the lock that "
                    "keeps a second service off this directory", self.path, why)
        return False

    def release(self) -> None:
        """Give the lock up (the last holder of this process closes it)."""
        if not self.held:
            return
        self.held = False
        entry = StateLock._held[self.path]
        entry[1] -= 1
        if entry[1] == 0:
            del StateLock._held[self.path]
            os.close(entry[0])


class StateStore:
    """Load and save :class:`PersistedState` in a directory.

    Parameters
    ----------
    directory : path
        The state directory (created on the first save if needed).
    model : Model
        The machine model (for validation on load and save).
    """

    def __init__(self, directory: str | os.PathLike[str], model: Model) -> None:
        self.dir = Path(directory)
        self.model = model
        self.path = self.dir / FILENAME
        #: Files that could not be used on load (each moved aside).
        self.load_errors = 0
        #: Saves that failed (disk full, read-only, a state that would not load, ...).
        self.save_errors = 0
        #: Of :attr:`save_errors`: states refused because they would not load (the old file kept).
        self.save_refused = 0
        #: Temporary files of interrupted saves removed at start.
        self.temp_removed = 0
        #: Learned parameters dropped on load because the model has no parameter of that name.
        self.params_dropped = 0
        #: Saves failed in a row (0 once a save works again; 1 after a failed :meth:`probe`).
        self.failing = 0
        self._failing_since: float | None = None  # wall time of the first failure of the streak
        self.saves = 0
        self.last_error: str | None = None
        self.last_saved_wall: float | None = None  # wall time of this process's last good save
        self.quarantined: list[Path] = []
        self._deferred: list[str] | None = None  # why the file was refused, while its move is deferred

    def load(self, defer: bool = False) -> PersistedState | None:
        """The saved state, or None (missing or unusable: then logged, counted, moved aside).

        With ``defer`` an unusable file is moved aside (and said so) only at :meth:`settle`: a
        service that refuses its configuration after loading must leave the state as it found it
        (the right configuration's start may well use it).

        Never raises; reads at most :data:`MAX_BYTES`. Removes temporary files of interrupted saves first.
        """
        self._deferred = [] if defer else None
        self._remove_temp_files()
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            if os.path.lexists(self.path):
                self._bad("a symbolic link to nothing")
                return None
            log.info("no saved state in %s: starting from the model's parameters", self.dir)
            return None
        except OSError as exc:
            self._bad(f"cannot stat: {exc.strerror or exc}")
            return None
        if stat.S_ISDIR(st.st_mode):
            self._bad("a directory, not a file")
            return None
        if not stat.S_ISREG(st.st_mode):
            self._bad("not a regular file")
            return None
        if st.st_size > MAX_BYTES:
            self._bad(f"{st.st_size} bytes, larger than {MAX_BYTES // (1024 * 1024)} MiB (not read)")
            return None
        try:
            with open(self.path, "rb") as f:
                data = f.read(MAX_BYTES + 1)  # the file may have grown since the stat
        except OSError as exc:
            self._bad(f"cannot read: {exc.strerror or exc}")
            return None
        dropped: list[str] = []
        outdated: list[tuple[str, float, float, float]] = []
        try:
            state = decode(data, self.model, dropped, outdated)
        except StateError as exc:
            self._bad(str(exc))
            return None
        if outdated:
            self.params_dropped += len(outdated)
            log.warning("state file %s: dropped learned parameter(s) whose value in model %s changed since they were "
                        "learned (a new model file or edge.yaml model.parameters): %s; they start from the model's",
                        self.path, self.model.name, "; ".join(f"{k} learned {v:.6g} from {was:.6g}, the model now says "
                                                              f"{now:.6g}" for k, was, now, v in outdated))
        if dropped:
            self.params_dropped += len(dropped)
            kept = ", ".join(sorted(state.parameters)) or "none"
            log.warning("state file %s: dropped learned parameter(s) %s: model %s has no parameter of that name "
                        "(renamed or removed by a model update?); kept the others (%s)", self.path,
                        ", ".join(dropped), self.model.name, kept)
        self._say_loaded(state)
        return state

    def _say_loaded(self, state: PersistedState) -> None:
        """One line on what was loaded and how old it is by this host's clock; a WARNING for a
        state saved in the future (a clock set wrong before or now: its age cannot be trusted)."""
        what = (f"parameter version {state.param_version}, {len(state.parameters)} learned parameter(s), "
                + (f"the thermal state of {len(state.T)} nodes" if state.T else "no thermal state"))
        if state.saved_wall <= 0:
            log.info("loaded state file %s: %s", self.path, what)
            return
        age = time.time() - state.saved_wall
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(state.saved_wall))
        if age < -FUTURE_TOLERANCE_S:
            log.warning("loaded state file %s saved %.0f s in the future by this host's clock (%s UTC): a clock set "
                        "wrong, then or now; %s", self.path, -age, when, what)
        else:
            log.info("loaded state file %s: saved %s UTC, %.0f s ago; %s", self.path, when, max(age, 0.0), what)

    def probe(self) -> bool:
        """Can a save work? Create the directory if needed, write and remove a temporary file.

        A directory that cannot be written (read-only or full filesystem, permissions, cannot be
        created) is logged as an ERROR and counted as a failed save (:attr:`failing`); the service
        protects on without persistence and every save retries. Never raises.
        """
        tmp = self.path.with_name(f"{FILENAME}.tmp-probe-{os.getpid()}")  # removed at the next start if killed here
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                os.write(fd, b"{}")
            finally:
                os.close(fd)
            os.unlink(tmp)
        except OSError as exc:
            self._failed(f"cannot write the state directory {self.dir}: {exc.strerror or exc}",
                         "the service protects without persistence; every save retries")
            try:  # a write that failed after the create leaves the file
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
            return False
        return True

    def _failed(self, what: str, consequence: str) -> None:
        """Count a failed save (or probe) and log it if :func:`_worth_logging`."""
        self.save_errors += 1
        self.failing += 1
        self.last_error = what
        if self._failing_since is None:
            self._failing_since = time.time()
        if _worth_logging(self.failing):
            since = time.strftime("%H:%M:%S", time.gmtime(self._failing_since))
            kept = ("no state saved by this process yet" if self.last_saved_wall is None else
                    "the file holds the state of " + time.strftime("%H:%M:%S", time.gmtime(self.last_saved_wall)))
            log.error("%s; %s (%d failed in a row since %s UTC, %d in all; %s; next report after %d)", what,
                      consequence, self.failing, since, self.save_errors, kept,
                      self.failing * 2 if self.failing < 64 else self.failing + 64)

    def _remove_temp_files(self) -> None:
        try:
            names = [e.name for e in os.scandir(self.dir) if _TEMP_RE.match(e.name)]
        except OSError:
            return
        for name in names:
            try:
                os.unlink(self.dir / name)
            except OSError as exc:
                log.warning("cannot remove %s left by an interrupted save: %s", self.dir / name, exc.strerror or exc)
                continue
            self.temp_removed += 1
            log.warning("removed %s left by an interrupted save", self.dir / name)

    def settle(self) -> None:
        """Move aside the file a deferred :meth:`load` refused (the configuration accepted since)."""
        pending, self._deferred = self._deferred or [], None
        for why in pending:
            self._bad(why)

    def _bad(self, why: str) -> None:
        if self._deferred is not None:
            self._deferred.append(why)
            return None
        self.load_errors += 1
        self.last_error = why
        stamp = f"{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"
        aside = self.path.with_name(f"{_CORRUPT_PREFIX}{stamp}")
        n = 1
        while os.path.lexists(aside):  # two in one second (never overwrite the evidence)
            n += 1
            aside = self.path.with_name(f"{_CORRUPT_PREFIX}{stamp}-{n}")
        try:
            os.replace(self.path, aside)
            self.quarantined.append(aside)
            where = f"moved aside to {aside.name}"
        except OSError as exc:
            where = f"could not move it aside: {exc.strerror or exc}"
        log.error("state file %s is unusable: %s; %s; starting from the model's parameters", self.path, why, where)
        self._prune_corrupt()
        return None

    def _prune_corrupt(self) -> None:
        """Keep only the newest :data:`KEEP_CORRUPT` files moved aside (a crash loop must not fill the disk)."""
        try:
            aside = sorted((e for e in os.scandir(self.dir) if e.name.startswith(_CORRUPT_PREFIX)),
                           key=lambda e: e.stat(follow_symlinks=False).st_mtime_ns)
        except OSError:
            return
        for e in aside[:-KEEP_CORRUPT]:
            try:
                if e.is_dir(follow_symlinks=False):
                    shutil.rmtree(e.path)
                else:
                    os.unlink(e.path)
            except OSError as exc:
                log.warning("cannot remove old corrupt state %s: %s", e.path, exc.strerror or exc)

    def encode(self, state: PersistedState) -> bytes:
        """The bytes :meth:`save` would write, checked by :func:`decode` (parameters snapped onto bounds).

        Raises
        ------
        StateError
            The state would not load at the next start.
        """
        raw = state.as_json()
        if isinstance(raw["parameters"], dict):
            raw["parameters"] = self.model.snap_to_bounds(raw["parameters"])
        try:
            data = json.dumps(raw, separators=(",", ":"), allow_nan=False).encode()
        except (TypeError, ValueError) as exc:  # non-finite floats, numpy leftovers
            raise StateError(f"cannot be written as JSON: {exc}") from None
        decode(data, self.model)
        return data

    def save(self, state: PersistedState) -> bool:
        """Write atomically; False (logged, counted) on failure. Never raises.

        The state is first run through the load path's validation; one that would not load is
        refused and the previous file kept.
        """
        try:
            data = self.encode(state)
        except StateError as exc:
            self.save_refused += 1
            self._failed(f"refusing to save state to {self.path}: it would not load ({exc})", "keeping the previous file")
            return False
        tmp = self.path.with_name(f"{FILENAME}.tmp-{os.getpid()}")
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                view = memoryview(data)
                while view:
                    n = os.write(fd, view)
                    view = view[n:]
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
            try:
                dfd = os.open(self.dir, os.O_RDONLY)
                try:
                    os.fsync(dfd)
                finally:
                    os.close(dfd)
            except OSError:
                pass
        except OSError as exc:
            self._failed(f"cannot save state to {self.path}: {exc.strerror or exc}", "keeping the previous file")
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass
            return False
        if self.failing:
            log.warning("state saved again to %s after %d failed save(s) in a row", self.path, self.failing)
        self.failing = 0
        self._failing_since = None
        self.saves += 1
        self.last_saved_wall = time.time()
        return True

