"""mrcert as a library: a scene, a classifier, and the certificates of the command line.

Each class binds a torch classifier (images (B, C, H, W) in [0, 1] -> logits) to a
:class:`~mrcert.scenes.scene.Scene` (a coloured point cloud in a camera's frame, with the
intrinsics to render it) and to one method, and certifies the scene as the camera sees it from
a pose (a motion (6,): ``tx ty tz`` in metres, ``rx ry rz`` in radians; the scene's camera when
not given):

* :class:`CameraMotionSmoothing` -- :meth:`~CameraMotionSmoothing.certify` (Cohen's CERTIFY: a
  class and a radius of camera motion, with probability at least ``1 - alpha``) and
  :meth:`~CameraMotionSmoothing.predict` (PREDICT: the smoothed class or :data:`ABSTAIN`);
* :class:`PixelwiseSmoothing` -- :meth:`~PixelwiseSmoothing.certify`: every pose of an interval
  on one axis, for the pixel-noise smoothed classifier, or nothing;
* :class:`BoundPropagation` and :class:`ImageEnumeration` -- ``verify(half_width)``: every pose of
  ``[-half_width, half_width]`` on one axis, for the classifier itself and with certainty
  (image enumeration: complete on the translations and rz);
* :func:`attack`: the classifier's prediction at K camera motions of an interval.

They are what the command line runs (``mrcert task=certify``, ``task=attack``): the same method
classes, the same renderer and the same seeded draws, so ``certify(seed=S, index=i)`` gives the
certificate ``mrcert task=certify seed=S`` logs for test image ``i`` of a data set whose image
``i`` is this scene. docs/api.md has a runnable example.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from mrcert.core.attacks import Grid, Uniform
from mrcert.core.geometry import compose
from mrcert.core.methods.base import ABSTAIN, BaseClassifier, Certificate, CertifyRequest, Method
from mrcert.core.methods.bound_propagation import BoundPropagation as _BoundPropagation
from mrcert.core.methods.camera_motion import CameraMotionSmoothing as _CameraMotion
from mrcert.core.methods.enumeration import ImageEnumeration as _Enumeration
from mrcert.core.methods.pixelwise import PixelwiseSmoothing as _Pixelwise
from mrcert.core.models import predicted
from mrcert.core.sampling import SmoothedClassifier, image_generator
from mrcert.data.samples import SampleRenderer, TestSample
from mrcert.errors import MrcertError
from mrcert.scenes.scene import Scene

__all__ = [
    "ABSTAIN",
    "BoundPropagation",
    "CameraMotionSmoothing",
    "Certificate",
    "ImageEnumeration",
    "PixelwiseSmoothing",
    "Scene",
    "attack",
    "load_model",
]

CROP_SIGMAS = 6.0
"""How many sigmas of a smoothing distribution a scene's exact crop covers (``task.crop_sigmas``):
the crop changes no image, only how many points are projected."""


def _motion(pose) -> torch.Tensor | None:
    if pose is None:
        return None
    motion = torch.as_tensor(pose, dtype=torch.float64).reshape(-1)
    if motion.shape != (6,) or not bool(torch.isfinite(motion).all()):
        raise MrcertError(f"pose={pose!r} is not allowed: six finite numbers (tx ty tz in m, rx ry rz in rad)")
    return motion


@dataclass
class _Bound:
    """A method bound to a classifier and a scene."""

    model: nn.Module
    scene: Scene
    method: Method
    num_classes: int | None = None
    batch_size: int = 200
    device: torch.device | str = "cpu"

    def __post_init__(self):
        self.device = torch.device(self.device)
        if self.num_classes is None:  # read off one image of the scene
            with torch.inference_mode():
                image = self.scene.render(torch.zeros(1, 6, dtype=torch.float64))[0]
                self.num_classes = int(self.model(image.to(self.device)).shape[1])
        self._certifier = None

    @property
    def certifier(self):
        """The method bound to the classifier (built once: the deterministic methods read its graph)."""
        if self._certifier is None:
            base = BaseClassifier(self.model, int(self.num_classes), int(self.batch_size), self.device)
            self._certifier = self.method.certifier(base)
        return self._certifier

    def view(self, pose=None) -> SampleRenderer:
        """The scene seen from ``pose`` (the scene's camera when None), cropped exactly for the
        method's motions: motions (B, 6) -> images (B, C, H, W)."""
        motion = _motion(pose)
        scene = self.scene
        sample = TestSample.build(
            scene.points.detach().cpu().numpy(), scene.colors.detach().cpu().numpy(), scene.K, scene.height,
            scene.width, -1, scene.background, bound=self.method.crop_bound(CROP_SIGMAS), frame=motion,
        )  # fmt: skip
        return sample.to(self.device).renderer()

    def _certify(self, pose, request: CertifyRequest, seed: int, index: int) -> Certificate:
        return self.certifier.certify_sample(self.view(pose), request, image_generator(seed, index))


class CameraMotionSmoothing(_Bound):
    """Camera motion smoothing (CoRL 2022): the classifier smoothed over Gaussian camera motions
    of ``sigma`` on ``axis`` (or, with ``axes`` and ``sigmas``, on several, as Theorem 1 licenses).

    Guarantee: if :meth:`certify` returns class ``c`` with radius ``R``, then with probability at
    least ``1 - alpha`` over its draws the smoothed classifier answers ``c`` for every camera
    motion of ``|delta| < R`` on the axis (several axes: the ellipsoid of radius ``R`` in sigma
    units) from ``pose``."""

    def __init__(
        self, model: nn.Module, scene: Scene, axis: str = "tz", sigma: float = 0.1, *, axes=None, sigmas=None, **kw
    ):
        axes = tuple(axes) if axes is not None else (axis,)
        sigmas = tuple(float(s) for s in sigmas) if sigmas is not None else (float(sigma),)
        super().__init__(model, scene, _CameraMotion(axes, sigmas), **kw)

    def certify(self, pose=None, n0: int = 100, n: int = 100_000, alpha: float = 0.001, seed: int = 0, index: int = 0):
        """Cohen's CERTIFY at ``pose``: the class guessed on ``n0`` draws, its probability bounded
        on ``n`` more at level ``alpha``; :data:`ABSTAIN` with radius 0 when the bound is below 1/2.
        The draws are test image ``index``'s of a run seeded ``seed``."""
        return self._certify(pose, CertifyRequest(int(n0), int(n), float(alpha), 0.0), seed, index)

    def predict(self, pose=None, n: int = 1000, alpha: float = 0.001, seed: int = 0, index: int = 0) -> int:
        """Cohen's PREDICT at ``pose``: the smoothed class, or :data:`ABSTAIN`, wrong with
        probability at most ``alpha``."""
        smoothed: SmoothedClassifier = self.certifier
        return smoothed.predict(self.view(pose), int(n), float(alpha), image_generator(seed, index))


class PixelwiseSmoothing(_Bound):
    """Pixel-wise smoothing (Hu et al., AISTATS 2024): Gaussian pixel noise of ``sigma`` at
    ``frames`` evenly spaced poses of ``[-half_width, half_width]`` on ``axis``. Guarantee: a
    certificate of class ``c`` (radius ``half_width``) holds, with probability at least
    ``1 - alpha``, for the pixel-noise smoothed classifier at every pose of the interval."""

    def __init__(self, model, scene: Scene, axis: str, half_width: float, sigma: float = 0.25, frames: int = 21, **kw):
        super().__init__(model, scene, _Pixelwise(axis, float(sigma), float(half_width), int(frames)), **kw)

    def certify(self, pose=None, n0: int = 100, n: int = 10_000, alpha: float = 0.001, seed: int = 0, index: int = 0):
        """The interval certified around ``pose`` (radius ``half_width``), or :data:`ABSTAIN`."""
        request = CertifyRequest(int(n0), int(n), float(alpha), float(self.method.half_width))
        return self._certify(pose, request, seed, index)


class _Deterministic(_Bound):
    def verify(self, half_width: float, pose=None) -> Certificate:
        """Whether the classifier gives one class at every pose of ``[-half_width, half_width]`` on
        the axis around ``pose``: that class with radius ``half_width``, else :data:`ABSTAIN`
        (``details["outcome"]``: ``verified``, ``falsified`` with the pose found, or ``unknown``)."""
        if not float(half_width) > 0:
            raise MrcertError(f"half_width={half_width!r} is not allowed: a number > 0")
        if float(half_width) != self.method.half_width:
            self.method = dataclasses.replace(self.method, half_width=float(half_width))
            self._certifier = None
        return self._certify(pose, CertifyRequest(0, 0, 0.0, float(half_width)), 0, 0)


class BoundPropagation(_Deterministic):
    """Deterministic certification by bound propagation (interval bounds or CROWN) over pieces of
    the interval; sound: a verified image is classified alike at every pose of it."""

    def __init__(self, model, scene: Scene, axis: str = "tz", relaxation: str = "crown", max_pieces: int = 512, **kw):
        super().__init__(model, scene, _BoundPropagation(axis, 1e-3, relaxation, int(max_pieces), math.inf), **kw)


class ImageEnumeration(_Deterministic):
    """Exact certification by enumerating every image the interval renders (any one axis):
    verified or falsified, unknown only when ``max_bounds`` is spent."""

    def __init__(self, model, scene: Scene, axis: str = "tz", max_bounds: int = 4096, **kw):
        super().__init__(model, scene, _Enumeration(axis, 1e-3, max_bounds=int(max_bounds)), **kw)


def attack(
    model: nn.Module, scene: Scene, axis: str, radius: float, k: int = 100, kind: str = "uniform", seed: int = 0,
    index: int = 0, pose=None,
) -> tuple[torch.Tensor, np.ndarray]:  # fmt: skip
    """The K motions on ``axis`` in ``[-radius, radius]`` (``kind``: ``uniform`` draws them as
    ``task=attack`` does for test image ``index`` of a run seeded ``seed``; ``grid``: evenly
    spaced) and the classifier's prediction at each, around ``pose``."""
    kinds = {"uniform": Uniform, "grid": Grid}
    if kind not in kinds:
        raise MrcertError(f"kind={kind!r} is not allowed: one of {', '.join(kinds)}")
    motions = kinds[kind](kind, int(k), float(radius)).motions(axis, int(seed), int(index))
    moved = motions if pose is None else compose(_motion(pose).expand(len(motions), 6), motions)
    with torch.inference_mode():
        images = scene.render(moved)[0]
        return motions, predicted(model(images)).cpu().numpy()


def load_model(path, device: torch.device | str = "cpu") -> nn.Module:
    """The classifier a ``task=train`` checkpoint holds, in evaluation mode on ``device``."""
    from hydra.utils import instantiate

    from mrcert.core.models import Normalize, for_inference
    from mrcert.infra.checkpoints import read_checkpoint

    state = read_checkpoint(path)
    if not state.get("model_config"):
        raise MrcertError(f"checkpoint {str(path)!r} does not say which network it holds (no model_config)")
    model = nn.Sequential(Normalize(), instantiate(state["model_config"], num_classes=int(state["num_classes"])))
    model.load_state_dict(state["model"])
    return for_inference(model, device)
