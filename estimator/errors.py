"""One exception root for physfuse; the CLI turns these into one clear line."""


class PhysfuseError(Exception):
    """Root of every error physfuse reports to a user (bad config, model, data)."""


class ConfigError(PhysfuseError):
    """A configuration file or setting is invalid; the message names the key."""


class LogError(PhysfuseError):
    """A log cannot be read; the message names the file, topic or field."""


class MissingTopicError(LogError):
    """A topic the config marks as required is absent from the log or has no usable sample."""
