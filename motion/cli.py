"""What the command lines share: one-line errors with exit status 2, ``--debug``, plain help.

``python -m motion`` and ``python -m experiments`` both build their parser from
:class:`Parser` and run their work through :func:`run`: bad input (a ``ValueError`` -- every
error class of this project derives from it -- or an ``OSError``) prints one line,
``error: ...``, to stderr and returns 2; ``--debug`` prints the traceback first. A usage
mistake (unknown option, missing argument) is one line too, pointing at ``--help``.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from collections.abc import Callable

__all__ = ["EXIT_BAD_INPUT", "Parser", "UsageError", "one_line", "run"]

#: exit status for bad input (as argparse uses for usage errors)
EXIT_BAD_INPUT = 2


class UsageError(ValueError):
    """A command line that does not parse (unknown option, missing argument)."""


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors raise :class:`UsageError` (one line, naming
    the ``--help`` to read) instead of printing the usage and exiting; the description and
    epilog are printed as written (plain text)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def add_debug(parser: argparse.ArgumentParser, top: bool = True) -> None:
    """Add ``--debug`` (on the top parser with a default; on sub-commands without one, so
    ``--debug`` may come before or after the sub-command)."""
    parser.add_argument(
        "--debug",
        action="store_true",
        default=False if top else argparse.SUPPRESS,
        help="on bad input, print the traceback before the one-line error",
    )


def one_line(err: BaseException) -> str:
    """An exception's message on one line (an ``OSError`` as ``FILE: reason``)."""
    if isinstance(err, OSError) and err.strerror and err.filename is not None:
        text = f"{err.filename}: {err.strerror}"
    elif isinstance(err, KeyError) and err.args:
        text = str(err.args[0])
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())


def _is_setting(item: str) -> bool:
    return "=" in item and not item.startswith("-")


def _parse(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``parser.parse_args(argv)``, except that ``key=value`` settings may also come after
    an option that follows the first of them (``--video a.avi seed=1 --out o refine.x=2``):
    argparse takes one run of a ``nargs="*"`` positional and leaves later runs unrecognised.
    Those join the command's ``overrides`` in their order on the command line (every later
    run comes after the first); anything else unrecognised is the usual usage error."""
    args, extra = parser.parse_known_args(argv)
    if extra:
        if not (
            all(map(_is_setting, extra)) and isinstance(getattr(args, "overrides", None), list)
        ):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*args.overrides, *extra]
    return args


def run(
    parser: argparse.ArgumentParser,
    argv: list[str] | None,
    body: Callable[[argparse.Namespace], int | None],
    errors: tuple[type[BaseException], ...] = (ValueError, OSError),
) -> int:
    """Parse ``argv`` and call ``body(args)``; returns the exit status: ``body``'s (0 if
    None), 0 after ``--help``, :data:`EXIT_BAD_INPUT` after printing one line for a usage
    error or one of ``errors``, 130 on Ctrl-C."""
    try:
        args = _parse(parser, argv)
    except UsageError as err:
        print(f"error: {one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except SystemExit as done:  # --help, --version
        return done.code if isinstance(done.code, int) else 0
    try:
        return body(args) or 0
    except errors as err:
        if getattr(args, "debug", False):
            traceback.print_exc()
        print(f"error: {one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
