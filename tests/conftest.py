"""Shared test fixtures.

Real data comes through one accessor, :func:`shared_data`, which skips the test with a
clear reason when ``../shared/data`` (or ``$REGTRACK_SHARED_DATA``) is absent.
Sources (cite when used): Pelicano et al., Sensors 2021 / PLoS One 2024 (label maps);
Deng et al. 2015, DigiBreast (CC mammogram); peers/ (CalculiX, FEBio, SfePy results).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("REGTRACK_SHARED_DATA", REPO.parent / "shared" / "data"))
SAMPLE_CASES = REPO / "sample_cases"


def shared_data(*parts: str) -> Path:
    """Path inside ../shared/data; skip the calling test if it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not available: {p} (set REGTRACK_SHARED_DATA to the shared/data folder)")
    return p


@pytest.fixture
def shared():
    return shared_data
