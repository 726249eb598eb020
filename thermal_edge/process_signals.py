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
seconds of start-up (imports, model, state, bus) too.
"""
from __future__ import annotations

import signal

__all__ = ["EXIT_STATE_NOT_SAVED", "IGNORED_SIGNALS", "STOP_SIGNALS", "ignore_while_starting"]

#: Signals that stop the service cleanly (the state saved).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGQUIT)
#: Signals ignored (each would otherwise kill the process: no TE_Limits, no save).
IGNORED_SIGNALS = (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2, signal.SIGALRM)
#: Exit status of a clean stop whose final save failed (what was learned since the last good save is
#: lost): not 0, so that ``systemctl`` shows the unit failed and a stop that systemd did not ask for
#: restarts it.
EXIT_STATE_NOT_SAVED = 3


def ignore_while_starting() -> None:
    """Ignore :data:`IGNORED_SIGNALS` until the running service's handlers (which log them) replace
    this; call it first thing in the process's main thread."""
    for sig in IGNORED_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
