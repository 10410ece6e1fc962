"""One error base for the whole package, with specific subclasses.

Messages follow the "expected X, but got Y" shape so a user can fix the input
without reading the code.
"""

from __future__ import annotations


class BessDedError(Exception):
    """Base of every error raised by bess-ded."""


class ParameterError(BessDedError, ValueError):
    """A controller / fixed-point parameter is invalid (bad gain, Ts, dwell, band, Q format)."""

    def __init__(self, name: str, expected: str, got: object) -> None:
        self.name = name
        self.expected = expected
        self.got = got
        super().__init__(f"{name}: expected {expected}, but got {got!r}")


class ConfigError(BessDedError, ValueError):
    """A scenario or node configuration file is invalid. Names the file and the key."""

    def __init__(self, source: str, key: str, problem: str) -> None:
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__(f"{source}: [{key}] {problem}")


class FrameError(BessDedError):
    """A received CAN frame was rejected. ``cause`` is the diagnostics counter it lands in."""

    cause = "malformed"


class UnknownFrameError(FrameError):
    """A received frame on an ID the DBC does not define (counted as unknown_id)."""

    cause = "unknown_id"


class FrameLengthError(FrameError):
    """A received frame whose DLC is not its message's (counted as dlc)."""

    cause = "dlc"


class RangeError(FrameError):
    """A received signal outside its DBC range (counted as range)."""

    cause = "range"


class EncodeError(BessDedError, ValueError):
    """A frame could not be built: unknown message or signal name, missing signal, or a
    value outside the DBC's range. Raised on the transmit side, so it is a caller bug,
    not bus traffic (FrameError is for received frames)."""

    def __init__(self, name: str, expected: str, got: object) -> None:
        self.name = name
        self.expected = expected
        self.got = got
        super().__init__(f"{name}: expected {expected}, but got {got!r}")
