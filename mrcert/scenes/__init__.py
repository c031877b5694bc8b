"""Scenes: coloured point clouds with the camera that looks at them."""

from mrcert.scenes.scene import Scene, load_scene

__all__ = ["Scene", "load_scene"]
