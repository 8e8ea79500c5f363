"""One exception root for physfuse; the CLI turns these into one clear line."""

from pathlib import Path


class PhysfuseError(Exception):
    """Root of every error physfuse reports to a user (bad config, model, data)."""


class ConfigError(PhysfuseError):
    """A configuration file or setting is invalid; the message names the key."""


class LogError(PhysfuseError):
    """A log cannot be read; the message names the file, topic or field."""


class MissingTopicError(LogError):
    """A topic the config marks as required is absent from the log or has no usable sample."""


def output_dir(path: Path) -> Path:
    """`path` created (with its parents) for a command's --out, or a one-line error."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise PhysfuseError(f"--out {path}: cannot create the directory ({err.strerror})") from err
    return path
