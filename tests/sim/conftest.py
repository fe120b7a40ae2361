import sys
from pathlib import Path

import pytest

# The tests import their helpers as ``tests.sim.helpers``: keep the repository root
# importable whatever the rootdir/package layout pytest picks.
_ROOT = Path(__file__).resolve().parents[2]
if str(_ROOT) not in sys.path:
    sys.path.insert(0, str(_ROOT))

from harvest_qp.sim import SimRobot, build_vine_scene  # noqa: E402


@pytest.fixture(scope="module")
def default_scene():
    """The paper's default scene, built once per module (each SimRobot copies its model)."""
    return build_vine_scene()


@pytest.fixture
def blind_robot(default_scene):
    """A SimRobot in the default scene without camera (fast)."""
    return SimRobot(default_scene, camera=None)
