"""Small helpers shared by test modules of different packages."""

from __future__ import annotations

import numpy as np


def random_pose(rng: np.random.Generator, scale: float = 0.5) -> np.ndarray:
    """A C-ordered homogeneous pose with a uniformly random rotation (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    pose = np.eye(4)
    pose[:3, :3] = q
    pose[:3, 3] = scale * rng.normal(size=3)
    return pose
