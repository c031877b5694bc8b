"""Scenes: coloured point clouds with the camera that looks at them."""

from mrcert.scenes.scene import Scene

__all__ = ["Scene"]
