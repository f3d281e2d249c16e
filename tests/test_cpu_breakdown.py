"""tools/bench/cpu_breakdown.py: every probe still names a function the run calls, and a probed
function counts its calls and CPU time without changing what it returns."""

from __future__ import annotations

import importlib
from collections import Counter, defaultdict
from collections.abc import Iterator

import numpy as np
import pytest

from bench import cpu_breakdown
from bench.cpu_breakdown import PROBES, REBIND, Tally


@pytest.fixture
def restored() -> Iterator[None]:
    """Put every probed attribute back after the test."""
    saved = []
    for module_name, attribute, _, _ in PROBES:
        owner = importlib.import_module(module_name)
        if "." in attribute:
            class_name, attribute = attribute.split(".")
            owner = getattr(owner, class_name)
        saved.append((owner, attribute, owner.__dict__[attribute]))
    for module_name, name in REBIND:
        module = importlib.import_module(module_name)
        saved.append((module, name, getattr(module, name)))
    yield
    for owner, name, value in saved:
        setattr(owner, name, value)


def test_every_probe_and_rebinding_names_a_function(restored: None) -> None:
    tally = Tally(defaultdict(float), Counter())
    probed = cpu_breakdown.install(tally)
    for module_name, name in REBIND:
        assert getattr(importlib.import_module(module_name), name) is probed[name]
    assert len(probed) == len({attribute.split(".")[-1] for _, attribute, _, _ in PROBES})


def test_a_probe_counts_and_returns_what_the_function_returns(restored: None) -> None:
    from doseqslam_logs.verification import geometry
    from doseqslam_logs.verification.params import VerificationParameters

    tally = Tally(defaultdict(float), Counter())
    cpu_breakdown.install(tally)
    rng = np.random.default_rng(0)
    gray = (rng.random((240, 320)) * 255).astype(np.uint8)
    features = geometry.extract_features(gray, VerificationParameters())
    assert features.count > 0
    assert tally.calls["features (ORB; SIFT)"] == 1
    assert tally.seconds["features (ORB; SIFT)"] > 0
