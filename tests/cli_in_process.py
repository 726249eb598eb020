"""The ``thermal-edge`` command run in the test's own process (tests of every directory import it)."""
from __future__ import annotations

import subprocess


def te_here(*args: object) -> subprocess.CompletedProcess[str]:
    """``thermal-edge ARGS`` through :func:`thermal_edge.cli.main` in this process, output captured:
    the same entry point as ``python -m thermal_edge.cli`` without a new interpreter's start-up (about 1 s a call). The
    process's signal dispositions and root logger are restored afterwards (``run`` ignores SIGHUP
    & co. from its first line and installs its own log handler)."""
    import contextlib
    import io
    import logging
    import signal

    from thermal_edge.cli import main

    argv = [str(a) for a in args]
    saved = {s: signal.getsignal(s) for s in (signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2, signal.SIGALRM,
                                                signal.SIGTERM, signal.SIGINT, signal.SIGQUIT)}
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exc:  # argparse's usage errors
                code = exc.code if isinstance(exc.code, int) else 1
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
        for h in list(root.handlers):
            root.removeHandler(h)
        for h in handlers:
            root.addHandler(h)
        root.setLevel(level)
    return subprocess.CompletedProcess(["thermal-edge", *argv], code, out.getvalue(), err.getvalue())
