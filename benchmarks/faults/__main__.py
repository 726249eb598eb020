"""``python -m benchmarks.faults`` (``make bench-faults``): the fault bench from the checkout.

Exit status 0 when every case passed, 1 when one lost something or saw an unsafe event (or a
control case was not judged unsafe), 2 on a usage error.
"""
from __future__ import annotations

import argparse
import json
import sys

from . import CONTROLS, GROUPS, report_table, run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.faults", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="full lengths and counts (200 SIGKILLs, 60 s at 8,000 "
                                                        "frames/s, a 7-day soak, ...); default: the short form")
    ap.add_argument("--only", action="append", default=None, metavar="GROUP", choices=[*GROUPS, *CONTROLS],
                    help="run only this group (repeatable); the control group runs only when named: "
                         + ", ".join([*GROUPS, *CONTROLS]))
    ap.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    args = ap.parse_args(argv)
    r = run(full=args.full, only=args.only)
    print(json.dumps(r.to_dict(), indent=2, default=float) if args.json else report_table(r))
    return 1 if r.failed else 0


if __name__ == "__main__":
    sys.exit(main())
