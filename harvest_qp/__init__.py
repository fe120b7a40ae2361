"""harvest_qp: QP-based task-priority control for bimanual robotic harvesting.

Data flow: perception -> the paper's controllers (reference twists) -> QP tasks and
limits -> :class:`Solver` -> robot (simulation or real), with the viewer observing.
"""

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import (
    ConfigError,
    DimensionError,
    EpisodeError,
    HarvestQPError,
    InfeasibleProblemError,
    InvalidInputError,
    ModelError,
    SolverError,
    SolverNotAvailableError,
    UnknownFrameError,
)
from harvest_qp.pinv import PseudoInverseMapper
from harvest_qp.solver import QPProblem, Solution, Solver, solve_ik
from harvest_qp.task_controller import ControlStep, TaskController

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "Configuration",
    "ControlStep",
    "DimensionError",
    "EpisodeError",
    "HarvestQPError",
    "InfeasibleProblemError",
    "InvalidInputError",
    "ModelError",
    "PseudoInverseMapper",
    "QPProblem",
    "Solution",
    "Solver",
    "SolverError",
    "SolverNotAvailableError",
    "TaskController",
    "UnknownFrameError",
    "solve_ik",
]
