"""Robot description: UR5e data, the dual-arm layout and generated model files."""
