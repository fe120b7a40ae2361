"""Compiled geometry kernels for collision avoidance (capsule distances, damper rows)."""
