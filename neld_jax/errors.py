"""Exceptions that the command-line entry points turn into one clear error line."""


class NeldError(Exception):
    """Base class of every error that neld-jax reports to users without a traceback."""


class DataError(NeldError):
    """Bad input data: a missing or unreadable file, empty scans, invalid poses. The message names the file."""


class ConfigError(NeldError):
    """A configuration value that cannot be used."""
