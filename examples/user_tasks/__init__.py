"""A user's own QP tasks, kept outside harvest_qp (see ``04_custom_task_from_yaml.py``)."""
