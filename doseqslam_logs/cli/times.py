"""Time arguments: integer nanoseconds since the epoch, or RFC 3339 with up to 9 decimals."""

from __future__ import annotations

import argparse
import re
from datetime import datetime, timezone

from ..errors import UsageError

LOG_TIME_MAX = 2**64 - 1

_RFC3339 = re.compile(
    r"^(\d{4}-\d{2}-\d{2})[Tt ](\d{2}:\d{2}:\d{2})(?:\.(\d{1,9}))?([Zz]|[+-]\d{2}:\d{2})$"
)


def parse_time_ns(text: str) -> int:
    """`1700000000123456789` or `2023-11-14T22:13:20.123456789Z` -> nanoseconds since the epoch.

    Raises UsageError for anything else (a time zone is required in RFC 3339 form).
    """
    text = text.strip()
    if re.fullmatch(r"\d+", text):
        return _log_time(text, int(text))
    match = _RFC3339.match(text)
    if not match:
        raise UsageError(
            f"not a time: {text!r} (use nanoseconds since the epoch or RFC 3339, "
            "e.g. 2023-11-14T22:13:20.5Z)"
        )
    day, clock, fraction, zone = match.groups()
    zone = "+00:00" if zone in ("Z", "z") else zone
    try:
        moment = datetime.fromisoformat(f"{day}T{clock}{zone}")
    except ValueError as exc:
        raise UsageError(f"not a time: {text!r} ({exc})") from None
    seconds = int((moment - datetime(1970, 1, 1, tzinfo=timezone.utc)).total_seconds())
    return _log_time(text, seconds * 1_000_000_000 + int((fraction or "").ljust(9, "0")))


def _log_time(text: str, value: int) -> int:
    """`value` if a log time (an unsigned 64-bit count of ns since the epoch) can be it."""
    if not 0 <= value <= LOG_TIME_MAX:
        raise UsageError(f"not a log time: {text!r} (log times run from 1970 to 2554)")
    return value


def time_argument(text: str) -> int:
    """argparse type of -S/-E: parse_time_ns, its errors reported as argparse's (exit 2)."""
    try:
        return parse_time_ns(text)
    except UsageError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
