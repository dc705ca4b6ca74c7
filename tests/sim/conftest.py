"""Shared fixtures of the simulator tests: scenarios are generated once per session (they are deterministic)."""

from __future__ import annotations

import pytest

from jitterguard.sim import SCENARIO_NAMES, GroundTruthFrame, Scenario, make_scenario


@pytest.fixture(scope="session")
def scenarios() -> dict[str, Scenario]:
    """One 12 s scenario of every kind at 10 Hz."""
    return {name: make_scenario(name, seed=7, duration_s=12.0) for name in SCENARIO_NAMES}


@pytest.fixture(scope="session")
def all_frames(scenarios: dict[str, Scenario]) -> dict[str, list[GroundTruthFrame]]:
    """Every frame of every fixture scenario, sampled once."""
    return {name: list(sc) for name, sc in scenarios.items()}
