from pathlib import Path

import pytest

from carp.data.collect import CollectionSummary, collect_demonstrations

LIFT_DEMO_SEED = 500


@pytest.fixture(scope="session")
def lift_demo_collection(tmp_path_factory) -> tuple[Path, CollectionSummary]:
    """Two scripted Lift demos (absolute actions), collected once per test session."""
    path = tmp_path_factory.mktemp("collect") / "lift.hdf5"
    summary = collect_demonstrations("lift", num_demos=2, output_path=path, seed=LIFT_DEMO_SEED)
    return path, summary
