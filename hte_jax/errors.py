"""Exception types raised on bad user input."""


class ConfigError(ValueError):
    """A configuration value is out of range or inconsistent; the message names it."""
