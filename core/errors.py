"""The project's small exception hierarchy, built on the built-in exceptions.

Every error the ``planer`` command can report to a user derives from one of these, so the
command line turns it into a one-line message and a non-zero exit instead of a traceback.
"""

from __future__ import annotations


class PlanerError(Exception):
    """Base of all errors raised on purpose by this project."""


class ConfigError(PlanerError, ValueError):
    """A configuration file or value is missing or invalid; the message names the key."""


class MeasurementError(PlanerError, ValueError):
    """An image pair cannot be measured (bad images, implausible result)."""


class RegistrationError(MeasurementError):
    """The two images of a pair cannot be registered with enough confidence."""


class FieldbusError(PlanerError, OSError):
    """A fieldbus (Modbus TCP, CAN) is unreachable, timed out or refused a request."""


class ModbusRefused(FieldbusError):
    """The Modbus server answered with an exception code (e.g. illegal address or value)."""
