"""QP tasks: one task per file."""

from harvest_qp.tasks.damping_task import DampingTask
from harvest_qp.tasks.frame_pose_task import FramePoseTask
from harvest_qp.tasks.frame_twist_task import FrameTwistTask
from harvest_qp.tasks.posture_task import PostureTask
from harvest_qp.tasks.relative_frame_task import RelativeFrameTask
from harvest_qp.tasks.task import HARD, Task
from harvest_qp.tasks.wrist_singularity_task import WristSingularityTask

__all__ = ["HARD", "DampingTask", "FramePoseTask", "FrameTwistTask", "PostureTask", "RelativeFrameTask", "Task",
           "WristSingularityTask"]
