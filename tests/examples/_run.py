"""Run an example script as a user does: ``python examples/NAME.py ARGS`` in a child process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin

from harvest_qp.robot.paths import urdf_path

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def run_example(name: str, *args: str, timeout: float = 120.0) -> str:
    """Run ``examples/<name>.py`` headless with ``sys.executable``; returns its stdout (asserts exit 0)."""
    env = dict(os.environ)
    env.setdefault("MPLBACKEND", "Agg")
    # The child imports this checkout's harvest_qp, as the test process does.
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(ROOT), env.get("PYTHONPATH"))))
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / f"{name}.py"), *args],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env,
    )  # fmt: skip
    assert proc.returncode == 0, f"{name} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def pinocchio_frame_positions(q: np.ndarray, frame: str) -> np.ndarray:
    """(n, 3) world positions of ``frame`` for each row of ``q`` (n, 12), straight from the URDF."""
    model = pin.buildModelFromUrdf(str(urdf_path()))
    data = model.createData()
    fid = model.getFrameId(frame)
    out = []
    for row in np.atleast_2d(q):
        pin.framesForwardKinematics(model, data, np.asarray(row, float))
        out.append(data.oMf[fid].translation.copy())
    return np.array(out)


def true_stem_base(seed: int) -> np.ndarray:
    """The lab's ground-truth stem base [m] of the episode scene for ``seed`` (0: the default scene)."""
    from harvest_qp.sim import VineSceneParams, build_vine_scene

    params = VineSceneParams.sample(seed) if seed > 0 else VineSceneParams(seed=0)
    return np.asarray(build_vine_scene(params).stem_base, float)
