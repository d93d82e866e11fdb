"""Shared plumbing of the command-line entry points (neld_jax.commands, bin/): absl flags with an ml_collections config
file, logging set-up, and one clear error line (no traceback) for bad input or a bad config.

The config is validated (neld_jax.config.validate) once its file and overrides are applied, before the command reads
anything. An error inside the user's config file is one line naming the file and line. NELD_TRACEBACK=1 in the
environment shows every such error with its full traceback instead.
"""

from __future__ import annotations

import logging
import os
import sys
import traceback
from typing import Callable

from neld_jax.errors import NeldError

TRACEBACK_VARIABLE = "NELD_TRACEBACK"  # set to 1: errors come with their tracebacks, not as one line


def _tracebacks_wanted() -> bool:
    return os.environ.get(TRACEBACK_VARIABLE, "").strip() not in ("", "0")


def _fail(message: str) -> None:
    print(f"error: {message}", file=sys.stderr)
    sys.exit(1)


def _run_guarded(argv, run: Callable[[], int | None], log_level: int, log_format: str, interrupted: str):
    """The body every entry point shares: no stray arguments, logging set up, and run() with its bad input or
    bad file turned into one line on stderr (exit 1). Returns run()'s exit code."""
    if len(argv) > 1:
        _fail(f"unexpected arguments: {' '.join(argv[1:])}")
    logging.basicConfig(level=log_level, format=log_format, datefmt="%H:%M:%S", force=True)
    logging.getLogger("absl").setLevel(logging.WARNING)  # orbax logs every file it writes at INFO
    try:
        return run()
    except (NeldError, OSError) as e:
        if _tracebacks_wanted():
            raise
        _fail(str(e) if isinstance(e, NeldError) else _short(e))  # a missing config file: its last line names it
    except KeyboardInterrupt:
        _fail(interrupted)


def _usage(doc: str | None) -> None:
    """--help prints the command's own docstring (absl reads __main__'s; a console script's has none)."""
    if doc:
        sys.modules["__main__"].__doc__ = doc


def main_with_config(job: Callable, doc: str | None = None) -> None:
    """Parse `--config=FILE[:budget]` and overrides, validate the config, then run job(config); errors become one
    line on stderr."""
    from absl import app, flags

    _usage(doc)
    from ml_collections import config_flags

    from neld_jax.config import validate

    config_flags.DEFINE_config_file(
        "config", None, "Config file (configs/*.py), optionally with ':budget'.", lock_config=True
    )
    flags.mark_flags_as_required(["config"])

    def main(argv):
        _run_guarded(
            argv,
            lambda: job(validate(flags.FLAGS.config)),
            logging.INFO,
            "%(asctime)s %(levelname)s %(name)s: %(message)s",
            "interrupted; rerun the same command to resume from the last checkpoint",
        )

    app.run(main, flags_parser=_parse_flags)


def main_with_flags(job: Callable[[], int | None], log_level: int = logging.INFO, doc: str | None = None) -> None:
    """For entry points with plain absl flags and no config: run job() (its return value is the exit code);
    a bad flag, bad input or a missing file is one line on stderr."""
    from absl import app

    _usage(doc)

    def main(argv):
        return _run_guarded(argv, job, log_level, "%(levelname)s %(name)s: %(message)s", "interrupted")

    app.run(main, flags_parser=_parse_flags)


def _parse_flags(argv):
    """absl's parser, but a bad flag, an unknown config field or an error in the config file is one line, not a
    usage dump or traceback."""
    from absl import flags

    try:
        return flags.FLAGS(argv)
    except Exception as e:  # noqa: BLE001 - whatever the user's config file raised
        if _tracebacks_wanted():
            raise
        config_file = _config_file(argv)
        where = _line_in_file(e, config_file) if config_file else ""
        if where and not isinstance(e, NeldError):
            message = e.msg if isinstance(e, SyntaxError) else _short(e)  # a syntax error's text less its position
            _fail(
                f"{where}: {e.__class__.__name__}: {message} (the config file; {TRACEBACK_VARIABLE}=1 shows the "
                "traceback)"
            )
        if isinstance(e, (KeyError, AttributeError)) and not where:
            _fail(_unknown_field(e, argv))
        if isinstance(e, (flags.Error, KeyError, AttributeError, ValueError, TypeError, FileNotFoundError, NeldError)):
            _fail(f"{where + ': ' if where else ''}{_short(e)}")
        raise


def _unknown_field(e: Exception, argv) -> str:
    """The line for an override of a field the config lacks (ml_collections raises a KeyError, in an
    AttributeError, whose text is the field's name and a guess)."""
    key_error = e if isinstance(e, KeyError) else e.__context__
    lines = str(key_error.args[0] if isinstance(key_error, KeyError) and key_error.args else e).splitlines()
    name = lines[0].strip("'\"") if lines else ""
    given = [arg.split("=", 1)[0][len("--config.") :].split(".") for arg in argv if arg.startswith("--config.")]
    parts = next((p for p in given if name in p), [name])
    guess = f" ({lines[-1].strip()})" if len(lines) > 1 else ""
    return f"--config.{'.'.join(parts)}: the config has no field {'.'.join(parts[: parts.index(name) + 1])}{guess}"


def _config_file(argv) -> str:
    """The file of --config=FILE[:ARGUMENT] in argv ("" if none)."""
    for i, arg in enumerate(argv):
        value = argv[i + 1] if arg in ("--config", "-config") and i + 1 < len(argv) else ""
        if arg.startswith(("--config=", "-config=")):
            value = arg.split("=", 1)[1]
        if value:
            path = value.rsplit(":", 1)[0] if ":" in os.path.basename(value) else value
            return os.path.abspath(path)
    return ""


def _line_in_file(e: BaseException, path: str) -> str:
    """ "FILE:LINE" of the deepest line of `path` where e (or the exception it came from) was raised: a syntax
    error's own position, else the traceback's frames; "" when none of them is in the file."""
    while e is not None:
        if isinstance(e, SyntaxError) and e.filename and os.path.abspath(e.filename) == path:
            return f"{e.filename}:{e.lineno}"
        frames = [f for f in traceback.extract_tb(e.__traceback__) if os.path.abspath(f.filename) == path]
        if frames:
            return f"{frames[-1].filename}:{frames[-1].lineno}"
        e = e.__cause__ or e.__context__
    return ""


def _short(e: Exception) -> str:
    text = str(e).strip().splitlines()
    return text[-1].strip() if text else e.__class__.__name__
