"""The plug point of a certification method: a certifier that takes the base classifier and a
test sample and returns a certificate, and what else the method serves.

A method is built once from the config (``method`` and ``motion`` groups); the evaluation tasks
bind it to the trained base classifier (:meth:`Method.certifier`) and hand each test sample's
:data:`Render` to the certifier. What a method serves besides ``task=certify`` it declares in
:attr:`Method.serves` (:data:`SERVICES`); config validation refuses any other task before a
run exists, naming the method and what it serves. Three implementations:

* the two smoothing methods, on the sampling engine of :mod:`mrcert.core.sampling` (vote
  counting, Cohen's CERTIFY and PREDICT, ABSTAIN): camera motion smoothing
  (:class:`~mrcert.core.methods.camera_motion.CameraMotionSmoothing`, ``method=camera_motion``) and
  pixel-wise smoothing (:class:`~mrcert.core.methods.pixelwise.PixelwiseSmoothing`, ``method=pixelwise``);
* deterministic verification by bound propagation
  (:class:`~mrcert.core.methods.bound_propagation.BoundPropagation`, ``method=bound_propagation``).

A further method is its own module (a subclass of :class:`Method`), one line of
:data:`mrcert.core.methods.METHODS`, its schema in :mod:`mrcert.core.methods.schemas` and its
YAML in ``conf/method/``; nothing in ``mrcert/infra/``, ``mrcert/tasks/`` or
``mrcert/reporting/`` names a method (``tests/test_method_plug.py``).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, runtime_checkable

import torch
from omegaconf import DictConfig

from mrcert.core.axes import AXES, axis_index, unit
from mrcert.core.crop import CropBound
from mrcert.errors import ConfigError

ABSTAIN = -1
"""A certifier's or smoothed classifier's answer when it cannot decide."""

SERVICES = {
    "train": "an augmented model's training (its training-time perturbation)",
    "smooth": "task=smooth (PREDICT, the smoothed benign accuracy)",
    "attack": "task=attack (PREDICT at attacked poses)",
    "sequential": "task.sequential (sequential CERTIFY)",
}
"""What a method may serve besides ``task=certify`` (:attr:`Method.serves`)."""

Render = Callable[[torch.Tensor], torch.Tensor]
"""A test sample as a certifier sees it: motions (B, 6) -> images (B, C, H, W), the sample
re-rendered under each motion (:meth:`~mrcert.data.samples.TestSample.renderer`)."""


@runtime_checkable
class SceneRender(Protocol):
    """A :data:`Render` that also shows the scene it renders, for a method that reasons about
    the cloud itself (bounds on the images between poses): :class:`~mrcert.data.samples.SampleRenderer`."""

    K: torch.Tensor
    """The camera intrinsics (3, 3)."""
    background: float
    """The colour of an empty pixel."""
    height: int
    width: int
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
    n: int = 0  # samples classified after the class guess (sequential CERTIFY has none; several frames add up)
    unit: str = ""  # the radius's unit (the view's for one view, the region's for a method's certify)
    # How far a method's own condition is from holding (pixel-wise smoothing: the smallest, over
    # pieces, of the better end frame's radius less its bound; bound propagation: the smallest
    # lower bound of the logit margin over the pieces); NaN for a method that has none.
    margin: float = float("nan")
    details: dict[str, Any] = field(default_factory=dict)
    """The values of the method's own log columns (:attr:`Method.log_columns`)."""
    n0: int = 0
    """Samples classified to guess the class, per estimate (Cohen's n0; none for sequential
    CERTIFY, which guesses on its estimation samples, or for a method that draws none)."""


@dataclass(frozen=True)
class CertifyRequest:
    """What ``task=certify`` asks of a certifier (``task.*`` and ``motion.radius``); a method
    uses what applies to it."""

    n0: int
    n: int
    alpha: float
    radius: float
    sequential: bool = False
    look: int = 40


@dataclass
class BaseClassifier:
    """The trained base classifier a certifier is bound to, with how to run it."""

    model: torch.nn.Module
    num_classes: int
    batch_size: int = 200
    device: torch.device | str = "cpu"
    overlap: bool = False
    """Render the next batch while the model classifies this one (pays off on a GPU)."""
    render_batch: int | None = None


class Certifier(Protocol):
    """A method bound to a base classifier (:meth:`Method.certifier`)."""

    def certify_sample(self, render: Render, request: CertifyRequest, generator: torch.Generator) -> Certificate:
        """The certificate of one test sample (its draws, if any, from ``generator``)."""
        ...


def single_axis(motion: DictConfig) -> str:
    """``motion.axis`` of a one-axis motion config (no ``motion.axes``)."""
    axis = str(motion.axis)
    if axis not in AXES:
        raise ConfigError("motion.axis", axis, f"one of {', '.join(AXES)} (several: motion.axes, with motion.sigmas)")
    return axis


class Method(ABC):
    """A certification method (see the module docstring). Implementations are frozen dataclasses."""

    axes: tuple[str, ...]
    """The motion axes it certifies against (one, or several for Theorem 1's combinations)."""

    @property
    @abstractmethod
    def noise_scales(self) -> tuple[float, ...]:
        """Its noise scales as the certify log records them (column ``sigma``), one per axis
        (motion units) or one (pixel units); none for a method without noise."""

    serves: ClassVar[frozenset[str]] = frozenset()
    """What it serves besides ``task=certify``: keys of :data:`SERVICES`."""
    log_columns: ClassVar[tuple[str, ...]] = ()
    """Columns of its own that the certify log gets after the common ones (:attr:`Certificate.details`)."""

    @classmethod
    @abstractmethod
    def from_config(cls, method: DictConfig, motion: DictConfig) -> Method:
        """The method the ``method`` and ``motion`` config groups describe; a value it cannot
        serve raises :class:`~mrcert.errors.ConfigError` naming the key."""

    @abstractmethod
    def certifier(self, base: BaseClassifier) -> Certifier:
        """The method bound to the base classifier, built once per evaluation."""

    @property
    def axes_label(self) -> str:
        """The motion axes it certifies against, as logs and tables name them (``tz``, ``tx+ty+tz+rz``)."""
        return "+".join(self.axes)

    @property
    def single(self) -> bool:
        return len(self.axes) == 1

    @property
    def sigma_unit(self) -> str:
        """The unit of :attr:`noise_scales` (one per axis, joined by ``+``)."""
        return ""

    # --- training (a method that serves "train") -----------------------------------------------
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

    # --- what a certificate means ------------------------------------------------------------
    @property
    @abstractmethod
    def region_unit(self) -> str:
        """The unit of a certificate's radius: that of the region it certifies."""

    def judged_at(self, radius: float) -> float:
        """The radius a certify run's certified accuracy is reported at, for the motion's
        ``radius`` (``motion.radius``): that radius, unless the method certifies a region of
        its own."""
        return radius

    def largest_radius(self, n: int, alpha: float) -> float:
        """The largest radius a certificate can hold when it drew ``n`` samples at level
        ``alpha``: a logged radius beyond it was not computed by this method. A method that
        certifies a region of its own reaches that region at most."""
        return self.judged_at(math.inf)

    @abstractmethod
    def region(self) -> str:
        """What a certified radius R means."""

    @abstractmethod
    def crop_bound(self, sigmas: float) -> CropBound:
        """The motions a test sample's exact crop must cover (``sigmas``: the evaluation's
        ``task.crop_sigmas``)."""


class WholeInterval:
    """For a method that certifies the whole interval ``[-half_width, half_width]`` on one
    ``axis`` or nothing (its dataclass fields ``axis`` and ``half_width``): a certificate's
    radius is ``half_width`` or 0, and the exact crop covers the interval."""

    def __post_init__(self):
        axis_index(self.axis)  # its values' ranges: the method's config schema

    @classmethod
    def interval_axis(cls, motion: DictConfig, name: str) -> str:
        """``motion.axis``, refused in one line when the motion has several (``method=name``)."""
        if motion.get("axes"):
            raise ConfigError("motion", motion.get("axis"), f"one axis: method={name} certifies an interval on one")
        return single_axis(motion)

    @property
    def axes(self) -> tuple[str, ...]:
        return (self.axis,)

    @property
    def region_unit(self) -> str:
        """The interval's half-width, in the axis's unit."""
        return unit(self.axis)

    def judged_at(self, radius: float) -> float:
        """The interval's half-width: all a certificate can reach."""
        return self.half_width

    def crop_bound(self, sigmas: float) -> CropBound:
        """Every motion of the interval."""
        return CropBound.covering({self.axis: self.half_width})
