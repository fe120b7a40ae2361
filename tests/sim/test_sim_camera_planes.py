"""Ray caster: plane rectangles, drawn a row span at a time, against the scalar intersection code."""

from __future__ import annotations

import mujoco
import numpy as np

from harvest_qp.sim import CameraConfig
from harvest_qp.sim.camera import RayCastCamera
from tests.sim.helpers import look_at
from tests.sim.test_sim_fastpaths import _cast_every_geom

# Two finite tilted planes whose edges are in view (seen from behind in some views), an
# infinite one (size 0) as the floor, and a ball and a capsule partly in front of them.
PLANES_XML = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" pos="0 0 -0.4" size="0 0 0.01"/>
    <geom name="board" type="plane" pos="1.0 0 0" euler="0 -80 10" size="0.25 0.15 0.01"/>
    <geom name="tile" type="plane" pos="0.8 -0.3 0.1" euler="20 -60 0" size="0.08 0.2 0.01"/>
    <geom name="ball" type="sphere" pos="0.7 0.05 0.02" size="0.05"/>
    <geom name="bar" type="capsule" fromto="0.6 -0.2 -0.1 0.75 0.2 0.05" size="0.02"/>
  </worldbody>
</mujoco>
"""


def test_plane_spans_equal_the_scalar_plane_test_bit_for_bit():
    """Bug caught: the branch-free plane span (distances for a whole row span, then the merge)
    departing from the scalar plane test: a rectangle bound left out or taken on the wrong
    coordinate, a miss kept as a hit, or a different rounding of t.
    Oracle: a brute-force kernel casting every pixel ray against every geom with the scalar
    per-geom routine (``_geom_local``), in id order; distances and ids must agree exactly on
    views that see the rectangles' edges, their back faces and the floor.
    """
    model = mujoco.MjModel.from_xml_string(PLANES_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cam = RayCastCamera(model, CameraConfig(downsample=6, max_depth=3.0, raycast_engine="numba"))
    rng = np.random.default_rng(7)
    ids, lengths = np.empty(cam.n_pixels, np.int32), np.empty(cam.n_pixels)
    hits = np.zeros(model.ngeom, int)
    for k in range(30):
        eye = rng.normal(0.0, 0.25, 3)
        if k % 3 == 2:
            eye[0] = 1.6 + rng.uniform(0.0, 0.4)  # behind the board and the tile
        target = np.array([0.9, -0.1, 0.0]) + rng.normal(0.0, 0.2, 3)
        pose = look_at(eye, target, rng.normal(0.0, 0.3, 3) + (0.0, 0.0, 1.0))
        dist, geomid = cam.cast(data, pose)
        _cast_every_geom(
            cam._rays_c, np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]), cam._geom_type,
            model.geom_size, data.geom_xpos, data.geom_xmat, cam._mask, cam._cutoff, ids, lengths,
        )  # fmt: skip
        np.testing.assert_array_equal(geomid, ids)
        assert dist.tobytes() == lengths.tobytes()
        np.add.at(hits, ids[ids >= 0], 1)
    # Every plane and both occluders were seen.
    assert np.all(hits > 200), hits
