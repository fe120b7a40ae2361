"""The scene's static capsules that the controller knows (``qp.environment``) and the metrics score against."""

from __future__ import annotations

from harvest_qp.exceptions import ConfigError, InvalidInputError

__all__ = ["environment_capsules_for"]


def environment_capsules_for(robot, names) -> list:
    """The capsules of the scene bodies ``names`` of the simulated ``robot`` (model and data);
    a missing body is a :class:`~harvest_qp.exceptions.ConfigError` naming ``qp.environment``."""
    from harvest_qp.runtime.task_episode import environment_capsules

    try:
        return environment_capsules(robot.model, robot.data, names)
    except (InvalidInputError, KeyError) as err:
        raise ConfigError(f"qp.environment: {err}") from None
