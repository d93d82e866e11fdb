"""Shared plumbing of the command-line entry points (neld_jax.commands, bin/): absl flags with an ml_collections config file,
logging set-up, and one clear error line (no traceback) for bad input or a bad config.
"""

from __future__ import annotations

import logging
import sys
from typing import Callable

from neld_jax.errors import NeldError


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
        _fail(str(e))
    except KeyboardInterrupt:
        _fail(interrupted)


def _usage(doc: str | None) -> None:
    """--help prints the command's own docstring (absl reads __main__'s; a console script's has none)."""
    if doc:
        sys.modules["__main__"].__doc__ = doc


def main_with_config(job: Callable, doc: str | None = None) -> None:
    """Parse `--config=FILE[:budget]` and overrides, then run job(config); errors become one line on stderr."""
    from absl import app, flags

    _usage(doc)
    from ml_collections import config_flags

    config_flags.DEFINE_config_file("config", None, "Config file (configs/*.py), optionally with ':budget'.",
                                    lock_config=True)
    flags.mark_flags_as_required(["config"])

    def main(argv):
        _run_guarded(argv, lambda: job(flags.FLAGS.config), logging.INFO,
                     "%(asctime)s %(levelname)s %(name)s: %(message)s",
                     "interrupted; rerun the same command to resume from the last checkpoint")

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
    """absl's parser, but a bad flag or an unknown config field is one line, not a usage dump or traceback."""
    from absl import flags

    try:
        return flags.FLAGS(argv)
    except flags.Error as e:
        _fail(_short(e))
    except (KeyError, AttributeError, ValueError, TypeError, FileNotFoundError, NeldError) as e:
        _fail(_short(e))


def _short(e: Exception) -> str:
    text = str(e).strip().splitlines()
    return text[-1] if text else e.__class__.__name__
