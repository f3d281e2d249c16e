"""Stable fingerprints of parameter sets: the same text and hash on every machine."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any


def canonical_json(values: Mapping[str, Any]) -> str:
    """Sorted keys, no spaces, floats by their shortest repr."""
    return json.dumps(values, sort_keys=True, separators=(",", ":"))


def fingerprint(values: Mapping[str, Any]) -> str:
    """The first 16 hex digits of the sha256 of `canonical_json(values)`."""
    return hashlib.sha256(canonical_json(values).encode()).hexdigest()[:16]
