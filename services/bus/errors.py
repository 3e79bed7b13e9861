"""The one exception hierarchy of Telerobot.

`ProtocolError` is raised by the codec for a message that breaks the wire contract;
`RpcError` carries one of the contract's method error codes (PROTOCOL.md §4) and is what a
queryable raises to send an error reply; `Unavailable` is what a caller gets when no
service answered at all.
"""

from __future__ import annotations

from typing import Literal, get_args

#: PROTOCOL.md §4's codes, plus `unavailable` (docs/protocol-extensions.md): the decision
#: server's reply when the service it forwards to is down.
ErrorCode = Literal[
    "bad_request", "not_ready", "unreachable", "limit", "estop", "busy", "internal", "unavailable"
]
ERROR_CODES: frozenset[str] = frozenset(get_args(ErrorCode))


class TelerobotError(Exception):
    """Base of every error this project raises on purpose."""


class ProtocolError(TelerobotError, ValueError):
    """A payload that breaks the wire contract. `field` names the offending field."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.reason = message


class RpcError(TelerobotError):
    """A method failed; `code` is one of the contract's error codes."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(f"{code}: {message}")
        self.code: ErrorCode = code
        self.message = message


class Unavailable(TelerobotError):
    """No reply at all: the service is absent (PROTOCOL.md §4)."""


class TimedOut(Unavailable):
    """The service is there but gave no reply within the timeout: what it was asked may
    still be under way (a motion may be running). Query its status before retrying."""


class ConfigError(TelerobotError, ValueError):
    """A bad configuration value, found at start-up. `key` names it."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"config key {key!r}: {message}")
        self.key = key
        self.reason = message


class AlreadyRunning(TelerobotError):
    """A singleton service found another instance of itself alive in the same cell (the same
    Zenoh network and namespace) at start-up, and refuses to start beside it."""


class ConnectFailed(TelerobotError):
    """A session could not be opened: nothing answered at the endpoints, or the router
    refused the login. The message is one line with the cause and what to check."""
