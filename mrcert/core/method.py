"""The plug point of a certification method: what it trains on, how it draws a test view's
noisy samples, and how it turns their votes into a certificate.

A method is built once from the config (``method`` and ``motion`` groups) and is then used by
every task: ``task=train`` renders an augmented model's training images under
:meth:`Method.training_motions` and perturbs each batch with :meth:`Method.perturb`;
:class:`~mrcert.core.smoothing.SmoothedClassifier` counts votes over :meth:`Method.views`
(PREDICT, the attack) and certifies with :meth:`Method.certify`. Two implementations:
camera motion smoothing (:class:`~mrcert.core.smoothing.CameraMotionSmoothing`, ``method=camera_motion``)
and pixel-wise smoothing (:class:`~mrcert.core.pixelwise.PixelwiseSmoothing`, ``method=pixelwise``).

A further method touches its own module (a subclass of :class:`Method`), one line of
:data:`mrcert.core.methods.METHODS` (its class, its schema, what its run keys leave out), its
schema in :mod:`mrcert.core.method_schemas` and its YAML in ``conf/method/``; nothing in
``mrcert/infra/`` or ``mrcert/tasks/`` names a method (``tests/test_method_plug.py``). What it
refuses (its parameters, a motion or a task mode it cannot serve) it says in
:meth:`Method.from_config`, which config validation calls before any run opens.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol, runtime_checkable

import torch
from omegaconf import DictConfig

from mrcert.core.crop import CropBound
from mrcert.core.geometry import AXES
from mrcert.errors import ConfigError

ABSTAIN = -1
"""The smoothed classifier's answer when it cannot decide at the requested confidence."""

Render = Callable[[torch.Tensor], torch.Tensor]
"""What a smoothed classifier classifies: motions (B, 6) -> images (B, C, H, W), a test sample
re-rendered under each motion (:meth:`~mrcert.data.samples.TestSample.renderer`); a method's
:meth:`Method.views` turns it into the noisy samples it votes over."""


@runtime_checkable
class SceneRender(Protocol):
    """A :data:`Render` that also shows the scene it renders, for a method that reasons about
    the cloud itself (pixel-wise smoothing bounds the images between its frames):
    :class:`~mrcert.data.samples.SampleRenderer`."""

    K: torch.Tensor
    """The camera intrinsics (3, 3)."""
    background: float
    """The colour of an empty pixel."""
    projected: int
    """The camera poses rendered so far (a certificate's rendering cost)."""

    def __call__(self, motions: torch.Tensor) -> torch.Tensor: ...

    def cloud_for(self, motions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Points (camera frame), colours and tie-break ranks holding every point that can land
        in the image for a motion within the bound of ``motions``."""
        ...


@dataclass
class Certificate:
    prediction: int
    radius: float
    count_a: int
    p_a_lower: float
    n: int = 0  # estimation samples drawn (the sequential mode may stop early; several frames add up)
    unit: str = ""  # the radius's unit (Method.view_unit for one view, Method.region_unit for a method's certify)
    # How far a method's own condition on its views is from holding (pixel-wise smoothing: the
    # smallest, over pieces, of the better end frame's radius less its bound; negative on the
    # piece an interval failed on); NaN for a method that has none.
    margin: float = float("nan")


def single_axis(motion: DictConfig) -> str:
    """``motion.axis`` of a one-axis motion config (no ``motion.axes``)."""
    axis = str(motion.axis)
    if axis not in AXES:
        raise ConfigError("motion.axis", axis, f"one of {', '.join(AXES)} (several: motion.axes, with motion.sigmas)")
    return axis


class ViewCertifier(Protocol):
    """What a method certifies with: Cohen's CERTIFY of one view
    (:meth:`mrcert.core.smoothing.SmoothedClassifier.certify_view`)."""

    def certify_view(
        self, render: Render, n0: int, n: int, alpha: float, generator: torch.Generator, center=None
    ) -> Certificate: ...


class Method(ABC):
    """A certification method (see the module docstring). Implementations are frozen dataclasses."""

    axes: tuple[str, ...]
    """The motion axes it certifies against (one, or several for Theorem 1's combinations)."""
    sigmas: tuple[float, ...]
    """Its noise scales, one per axis (motion units) or one (pixel units)."""
    sequential: ClassVar[bool] = False
    """Whether CERTIFY's sequential mode (``task.sequential``) applies: it certifies one view."""

    @classmethod
    @abstractmethod
    def from_config(cls, method: DictConfig, motion: DictConfig) -> Method:
        """The method the ``method`` and ``motion`` config groups describe; a value it cannot
        serve raises :class:`~mrcert.errors.ConfigError` naming the key."""

    @property
    def axes_label(self) -> str:
        """The motion axes it certifies against, as logs and tables name them (``tz``, ``tx+ty+tz+rz``)."""
        return "+".join(self.axes)

    @property
    def single(self) -> bool:
        return len(self.axes) == 1

    # --- training ------------------------------------------------------------------------------
    def training_motions(self, n: int, seed: int) -> torch.Tensor | None:
        """The motions (n, 6) an augmented model's ``n`` training images are rendered under, or
        None for the training poses themselves."""
        return None

    def training_key(self, seed: int) -> dict[str, Any] | None:
        """What defines :meth:`training_motions` (part of the image cache's key); None when
        the images are the training poses' own."""
        return None

    def perturb(self, images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """An augmented model's training batch as it trains on it (drawn from ``generator``)."""
        return images

    # --- smoothing and certification -----------------------------------------------------------
    @abstractmethod
    def views(self, render: Render, n: int, generator: torch.Generator, center: torch.Tensor | None):
        """The ``n`` noisy samples of the view seen after the camera motion ``center`` (None: the
        test pose): ``(render_batch, inputs)``, where ``render_batch(inputs[s:e])`` gives the
        images of samples ``s..e-1`` whatever the batches."""

    @abstractmethod
    def certify(
        self, smoothed: ViewCertifier, render: Render, n0: int, n: int, alpha: float, generator: torch.Generator
    ) -> Certificate:
        """CERTIFY one test sample with ``smoothed``'s base classifier; the radius is in motion units."""

    @abstractmethod
    def radius(self, p_a_lower: float) -> float:
        """The radius of Cohen's certificate at one view for a lower bound on ``pA``, in the
        units of the method's noise (:attr:`view_unit`)."""

    @property
    @abstractmethod
    def view_unit(self) -> str:
        """The unit of :meth:`radius`: Cohen's radius at one view, in the noise's space."""

    @property
    @abstractmethod
    def region_unit(self) -> str:
        """The unit of the radius :meth:`certify` returns: that of the region it certifies."""

    @property
    @abstractmethod
    def sigma_unit(self) -> str:
        """The unit of :attr:`sigmas` (one per axis, joined by ``+``)."""

    def judged_at(self, radius: float) -> float:
        """The radius a certify run's certified accuracy is reported at, for the motion's
        ``radius`` (``motion.radius``): that radius, unless the method certifies a region of
        its own."""
        return radius

    @abstractmethod
    def region(self) -> str:
        """What a certified radius R means."""

    @abstractmethod
    def crop_bound(self, sigmas: float) -> CropBound:
        """The motions a test sample's exact crop must cover (``sigmas``: the evaluation's
        ``task.crop_sigmas``)."""
