"""User-facing errors.

Anything a user can cause (a bad file, key, name, size or budget) raises
``PacketrtError`` with one line that names the cause; the CLI prints it and exits
with code 2, never with a traceback.
"""


class PacketrtError(Exception):
    """A user mistake, reported as one line and exit code 2."""


class SceneError(PacketrtError):
    """A scene file is missing or malformed; the message names file and line."""


class ConfigError(PacketrtError):
    """A config key, value or plugin name is not allowed; the message lists what is."""
