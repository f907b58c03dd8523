"""slipd's exception tree. Every error names where it happened and what was expected."""


class SlipdError(Exception):
    """Base of every error slipd raises on purpose; the CLI prints it and exits 2."""


class ConfigError(SlipdError):
    """A profile, DBC or configuration value is missing or wrong (names file and key)."""


class LogFormatError(SlipdError):
    """A log file line cannot be parsed (names file and line)."""


class CodecError(SlipdError):
    """A DBC/profile combination cannot be compiled into a codec plan."""


class DependencyError(SlipdError):
    """An optional dependency a subcommand needs is not installed (names the extra)."""
