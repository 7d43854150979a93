"""Fixtures shared by several test files: the shipped simulated objects (loaded once per module)."""
from __future__ import annotations

from pathlib import Path

import pytest

from elastoprobe.sim.objects import load_object

OBJECTS = Path(__file__).resolve().parents[1] / "config" / "objects"


@pytest.fixture(scope="module")
def ball():
    return load_object(OBJECTS / "rubber_ball.yaml")


@pytest.fixture(scope="module")
def composite():
    return load_object(OBJECTS / "composite.yaml")


@pytest.fixture(scope="module")
def user_object():
    return load_object(OBJECTS / "user_object.yaml")
