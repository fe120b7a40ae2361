"""Pictures of the harvester with MuJoCo's OpenGL renderer: the UR5e meshes, or the collision capsules.

The lab's model (:func:`harvest_qp.sim.build_vine_scene`) is the capsule robot alone (its
depth camera must see exactly what the controller's collision model is).
:meth:`SceneRenderer.for_spec` compiles a second model for drawing from the lab's
``VineScene.spec`` with Universal Robots' meshes added as visual-only geoms
(:mod:`harvest_qp.robot.meshes`); :meth:`SceneRenderer.render` copies the lab's joint state
into it, so the lab itself is never touched. ``show_capsules`` is the toggle that draws
the collision capsules (MuJoCo geom group 3) too, or instead with ``show_meshes=False``.

Needs an OpenGL context: set ``MUJOCO_GL=egl`` (headless Mesa) or ``osmesa`` before
``mujoco`` is first imported.

    import os; os.environ.setdefault("MUJOCO_GL", "egl")
    from harvest_qp.sim.render import SceneRenderer
    from harvest_qp.sim import SimRobot

    robot = SimRobot()
    renderer = SceneRenderer.for_spec(robot.scene.spec)
    image = renderer.render(robot.data, lookat=(0.45, 0.1, 1.1), distance=1.6, azimuth=200, elevation=-20)
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import mujoco
import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot.meshes import VISUAL_CLASS, VISUAL_GROUP, add_visual_meshes

__all__ = ["SceneRenderer", "COLLISION_GROUP"]

#: MuJoCo geom group of the robot's collision capsules (``robot_collision`` class).
COLLISION_GROUP = 3


class SceneRenderer:
    """Offscreen RGB (or segmentation) images of a MuJoCo model of the harvester.

    Args:
        model: the model to draw (e.g. compiled from ``robots/dual_ur5e/scene.xml``); its
            offscreen buffer is enlarged to the image size if needed.
        width, height: image size [pixels].
        show_meshes: draw the visual-only UR5e meshes (geom group 2).
        show_capsules: draw the robot's collision capsules (geom group 3).
        show_sites: draw the task frames' sites (group 4).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        width: int = 960,
        height: int = 540,
        show_meshes: bool = True,
        show_capsules: bool = False,
        show_sites: bool = False,
    ) -> None:
        if not isinstance(model, mujoco.MjModel):
            raise InvalidInputError(f"model must be a mujoco.MjModel, got {type(model).__name__}")
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, int) or not 16 <= value <= 4096:
                raise InvalidInputError(f"{name} must be an integer number of pixels in 16..4096, got {value!r}")
        self.model = model
        self.data = mujoco.MjData(model)
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        if not os.environ.get("MUJOCO_GL"):
            raise ModelError("SceneRenderer needs MUJOCO_GL set (egl or osmesa) before mujoco is imported")
        try:
            self._renderer = mujoco.Renderer(model, height=height, width=width)
        except Exception as error:  # no GL context available
            raise ModelError(
                f"cannot create an OpenGL renderer (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {error}"
            ) from error
        self.option = mujoco.MjvOption()
        self.set_visible(show_meshes=show_meshes, show_capsules=show_capsules, show_sites=show_sites)

    @classmethod
    def for_spec(cls, spec: mujoco.MjSpec, *, sky: bool = True, **kwargs) -> SceneRenderer:
        """A renderer of a copy of ``spec`` (e.g. a lab scene's ``VineScene.spec``) with the UR5e meshes added.

        The copy has the same bodies and joints as ``spec``'s model (meshes, textures and
        geoms only), so a state of that model can be drawn by :meth:`render`. ``sky``: a
        gradient sky instead of MuJoCo's black background.
        """
        if not isinstance(spec, mujoco.MjSpec):
            raise InvalidInputError(f"spec must be a mujoco.MjSpec, got {type(spec).__name__}")
        copy = spec.copy()
        if not any(g.classname.name == VISUAL_CLASS for g in copy.geoms):
            add_visual_meshes(copy)
        if sky and not any(t.type == mujoco.mjtTexture.mjTEXTURE_SKYBOX for t in copy.textures):
            copy.add_texture(name="render_sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                             builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, rgb1=[0.55, 0.7, 0.85],
                             rgb2=[0.08, 0.1, 0.15], width=256, height=256)  # fmt: skip
        try:
            model = copy.compile()
        except Exception as error:
            raise ModelError(f"the scene with the UR5e meshes does not compile: {error}") from error
        return cls(model, **kwargs)

    def set_visible(self, *, show_meshes: bool = True, show_capsules: bool = False, show_sites: bool = False) -> None:
        """Choose what is drawn: the UR5e meshes, the collision capsules (the toggle), the task sites."""
        self.option.geomgroup[:] = 0
        self.option.geomgroup[:3] = 1  # MuJoCo's default: groups 0-2 (floor, vine, meshes)
        self.option.geomgroup[VISUAL_GROUP] = int(bool(show_meshes))
        self.option.geomgroup[COLLISION_GROUP] = int(bool(show_capsules))
        self.option.sitegroup[:] = 0
        self.option.sitegroup[4] = int(bool(show_sites))

    def render(
        self,
        state: mujoco.MjData | NDArray[np.float64] | None = None,
        *,
        lookat: Sequence[float] = (0.45, 0.1, 1.05),
        distance: float = 1.7,
        azimuth: float = 200.0,
        elevation: float = -20.0,
        segmentation: bool = False,
    ) -> NDArray[np.uint8]:
        """One image (H, W, 3) uint8 from an orbit camera.

        Args:
            state: the joint state to draw: an ``MjData`` of a model with the same joints
                (e.g. ``SimRobot.data``), a ``qpos`` vector, or None (the model's ``qpos0``).
            lookat: point the camera looks at [m].
            distance: camera distance from ``lookat`` [m].
            azimuth, elevation: camera direction [deg] (MuJoCo's free camera convention).
            segmentation: return MuJoCo's segmentation image instead (channel 0: object id,
                channel 1: object type; -1 where nothing is drawn), int32.
        """
        qpos = self.model.qpos0 if state is None else (state.qpos if isinstance(state, mujoco.MjData) else state)
        qpos = np.asarray(qpos, dtype=float)
        if qpos.shape != (self.model.nq,):
            raise InvalidInputError(f"state must give {self.model.nq} joint positions (qpos), got shape {qpos.shape}")
        self.data.qpos[:] = qpos
        if isinstance(state, mujoco.MjData) and state.mocap_pos.shape == self.data.mocap_pos.shape:
            self.data.mocap_pos[:] = state.mocap_pos
            self.data.mocap_quat[:] = state.mocap_quat
        mujoco.mj_forward(self.model, self.data)
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        camera.lookat[:] = np.asarray(lookat, dtype=float)
        camera.distance = float(distance)
        camera.azimuth = float(azimuth)
        camera.elevation = float(elevation)
        r = self._renderer
        r.update_scene(self.data, camera=camera, scene_option=self.option)
        if segmentation:
            r.enable_segmentation_rendering()
            try:
                return r.render().copy()
            finally:
                r.disable_segmentation_rendering()
        return r.render().copy()

    def close(self) -> None:
        """Free the OpenGL context."""
        self._renderer.close()

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
