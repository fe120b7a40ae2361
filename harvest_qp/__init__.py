"""harvest_qp: QP-based task-priority control for bimanual robotic harvesting."""

__version__ = "0.1.0"
