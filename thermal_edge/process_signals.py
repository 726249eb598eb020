"""What ``thermal-edge run`` does with process signals, from its first line of Python to its exit.

- SIGTERM, SIGINT, SIGQUIT (:data:`STOP_SIGNALS`): a clean stop, the state saved; exit 0, or
  :data:`EXIT_STATE_NOT_SAVED` if that final save failed. SIGQUIT is a stop too: it is what
  ``Ctrl-\\`` and ``kill -QUIT`` ask of a daemon (nginx and many others), and its default action --
  die at once with a core -- would lose everything learned since the last save; ignoring it would
  leave SIGKILL, which loses it too.
- SIGHUP, SIGUSR1, SIGUSR2, SIGALRM (:data:`IGNORED_SIGNALS`): ignored, and logged by name (WARNING)
  once the service runs. There is no reload and no other command by signal, and by default each of
  them kills the process, which stops ``TE_Limits``: systemd's ``Restart=on-failure`` does not even
  restart a death by SIGHUP (it counts as a clean exit), and the others count towards
  ``StartLimitBurst``. SIGHUP is the likeliest (a logrotate ``postrotate``, a closed terminal).
- SIGPIPE: ignored by Python already.

This module is imported before anything heavy, so that :func:`ignore_while_starting` covers the
seconds of start-up (imports, model, state, bus) too: a stop signal then is remembered and honoured
as a clean stop once the service runs (:func:`stop_requested_while_starting`); a second one stops at
once, for a start-up that hangs.
"""
from __future__ import annotations

import os
import signal
from types import FrameType

__all__ = ["EXIT_STATE_NOT_SAVED", "IGNORED_SIGNALS", "STOP_SIGNALS", "ignore_while_starting",
           "stop_requested_while_starting"]

#: Signals that stop the service cleanly (the state saved).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGQUIT)
#: Signals ignored (each would otherwise kill the process: no TE_Limits, no save).
IGNORED_SIGNALS = (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2, signal.SIGALRM)
#: Exit status of a clean stop whose final save failed (what was learned since the last good save is
#: lost): not 0, so that ``systemctl`` shows the unit failed and a stop that systemd did not ask for
#: restarts it.
EXIT_STATE_NOT_SAVED = 3


_stop_while_starting: list[signal.Signals] = []


def _remember_stop(signum: int, frame: FrameType | None) -> None:
    if _stop_while_starting:  # the second: the start-up may hang, stop now as the signal would
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
    _stop_while_starting.append(signal.Signals(signum))


def ignore_while_starting() -> None:
    """Ignore :data:`IGNORED_SIGNALS` and remember a stop signal (:data:`STOP_SIGNALS`) until the
    running service's handlers replace these; call it first thing in the process's main thread.
    Otherwise a SIGTERM in the first 1.5 s would end the process by the signal's default action,
    with no log line."""
    for sig in IGNORED_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    for sig in STOP_SIGNALS:
        signal.signal(sig, _remember_stop)


def stop_requested_while_starting() -> signal.Signals | None:
    """The stop signal received while the service started (None if none)."""
    return _stop_while_starting[0] if _stop_while_starting else None
