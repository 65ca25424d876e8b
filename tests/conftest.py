"""Fixtures shared by the test modules."""

import pytest

import markerpose as mp


@pytest.fixture(scope="session")
def rig() -> mp.StereoRig:
    """The simulated paper-like rig (its cameras' ray grids are built once and shared)."""
    return mp.StereoRig.default()
