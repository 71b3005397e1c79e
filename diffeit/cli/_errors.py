"""How every `diffeit` command reports the user's errors: one line on stderr, exit status 2."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

# Bad input files and options are the user's to fix: one line, no traceback.
USER_ERRORS: tuple[type[Exception], ...] = (ValueError, FileNotFoundError, FileExistsError)


def reporting_user_errors(
    command: str, work: Callable[[argparse.Namespace], int], errors: tuple[type[Exception], ...] = USER_ERRORS
) -> Callable[[argparse.Namespace], int]:
    """`work` as a command's `run`: `errors` become "diffeit COMMAND: error: ..." on stderr and exit
    status 2; the others propagate."""

    def run(arguments: argparse.Namespace) -> int:
        try:
            return work(arguments)
        except errors as error:
            print(f"diffeit {command}: error: {error}", file=sys.stderr)
            return 2

    return run
