"""Errors that a user can fix: reported as one clear line, without a traceback."""


class MrcertError(Exception):
    """A problem with what the user asked for (config value, file, URI), not a bug."""


class ConfigError(MrcertError):
    """A config value outside what is allowed."""

    def __init__(self, key: str, value: object, allowed: str):
        self.key, self.value, self.allowed = key, value, allowed
        super().__init__(f"config value {key}={value!r} is not allowed: {allowed}")
