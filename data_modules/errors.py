"""Bad input as one line: which exceptions count, and how the line reads (every command uses these).

A reader's :class:`~data_modules.frame.DatasetError`, a missing mandatory config value and any
OSError (named by its path) are bad input: a command prints ``error: <where>: <problem>`` for them
and exits with status 2 instead of showing a traceback. Hydra's ``instantiate`` wraps a reader's
error in its own exception, so the cause chain is searched.
"""

from __future__ import annotations

import functools
import re
import sys
from collections.abc import Callable
from typing import Any

from omegaconf.errors import MissingMandatoryValue

from data_modules.frame import DatasetError

EXIT_BAD_INPUT = 2
BAD_INPUT: tuple[type[BaseException], ...] = (DatasetError, MissingMandatoryValue, OSError)


def find_cause(exc: BaseException, kinds: tuple[type[BaseException], ...] = BAD_INPUT) -> BaseException | None:
    """The first exception of ``kinds`` in ``exc``'s cause/context chain (``exc`` itself first), or None."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        if isinstance(current, kinds):
            return current
        current = current.__cause__ or current.__context__
    return None


def error_line(exc: BaseException) -> str:
    """``error: ...`` in one line for a bad-input exception."""
    if isinstance(exc, MissingMandatoryValue):
        key = getattr(exc, "full_key", None) or ""
        text = f"missing mandatory config value {key!r} (set it on the command line: {key}=...)" if key else str(exc)
    elif isinstance(exc, OSError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or type(exc).__name__}"
    else:
        text = str(exc) or type(exc).__name__
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return "error: " + re.sub(r"\s+", " ", first).strip()


def override_syntax_error(args: list[str]) -> str | None:
    """The ``error:`` line for the first command-line override Hydra's grammar cannot parse (e.g.
    ``hydra.run.dir=runs/a=b``: an unquoted ``=`` in a value), or None. Flags are left to Hydra."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    parser = OverridesParser.create()
    for arg in args:
        if arg.startswith("-") or "=" not in arg:
            continue
        try:
            parser.parse_overrides([arg])
        except OverrideParseException as exc:
            key, _, value = arg.partition("=")
            reason = re.sub(r"\s+", " ", str(exc).strip().splitlines()[0])
            return (f"error: {arg}: not a valid override ({reason}); quote a value that holds '=', spaces or brackets: "
                    f"{key}='{value}'")
    return None


def overrides_checked(main: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a ``@hydra.main`` entry point: an override Hydra cannot parse ends the command with one
    ``error:`` line and exit status 2 (Hydra itself prints several lines and exits with 1)."""

    @functools.wraps(main)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        line = override_syntax_error(sys.argv[1:])
        if line is not None:
            print(line, file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)
        return main(*args, **kwargs)

    return wrapper
