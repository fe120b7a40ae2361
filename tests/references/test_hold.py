"""The approach's hold reference (references/hold.py) against hand values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp.references import HoldPose


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("angle", [0.0, 0.3, -1.2])
def test_hold_twist_servoes_back_to_the_held_pose(angle):
    """A gripper moved by (0.01, -0.02, 0.03) m and turned by ``angle`` about z (the held pose turned
    about its own z first) gets -k [offset; angle z]. Catches: the gain's sign, the rotation error
    taken as R_hold R_g^T (the opposite turn), the rotation written into the linear slots."""
    k = 0.7
    held = np.eye(4)
    held[:3, :3] = _rot_z(0.4)
    held[:3, 3] = (0.3, 0.1, 0.9)
    pose = held.copy()
    pose[:3, :3] = _rot_z(angle) @ held[:3, :3]
    pose[:3, 3] += (0.01, -0.02, 0.03)
    np.testing.assert_allclose(HoldPose(held, k_hold=k).update(pose),
                               [-k * 0.01, k * 0.02, -k * 0.03, 0.0, 0.0, -k * angle], atol=1e-12)
