"""mrcert: certify and stress-test visual perception models against camera motion.

The library's face is :mod:`mrcert.api` (docs/api.md), its names importable from here
(``mrcert.CameraMotionSmoothing``, ``mrcert.Scene``, ...); they are imported on first use, so
that the command line's help and config checks never import torch."""

__version__ = "0.1.0"

API = ("ABSTAIN", "BoundPropagation", "CameraMotionSmoothing", "Certificate", "ImageEnumeration",
       "PixelwiseSmoothing", "Scene", "attack", "load_model")  # fmt: skip


def __getattr__(name: str):
    if name in API:
        from mrcert import api

        return getattr(api, name)
    raise AttributeError(f"module 'mrcert' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *API])
