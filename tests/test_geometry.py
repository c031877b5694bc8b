import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mrcert.core import geometry as g
from mrcert.core.axes import AXES, axis_index


def test_rotvec_matrix_match_scipy_and_round_trip(rng):
    n = rng.normal(size=(200, 3))
    rv = n / np.linalg.norm(n, axis=1, keepdims=True) * rng.uniform(0, np.pi - 1e-3, (200, 1))
    rv = np.concatenate([rv, [[0, 0, 0], [np.pi, 0, 0], [0, 0, np.pi - 1e-9], [1e-9, 0, 0]]])
    R = g.rotvec_to_matrix(torch.tensor(rv))
    np.testing.assert_allclose(R.numpy(), Rotation.from_rotvec(rv).as_matrix(), atol=1e-12)
    back = g.matrix_to_rotvec(R).numpy()
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), R.numpy(), atol=1e-9)
    np.testing.assert_allclose(back[:-4], rv[:-4], atol=1e-9)


@pytest.mark.parametrize("axis", ["rx", "ry", "rz"])
def test_one_axis_rotations_are_the_spec_matrices(axis):
    th = 0.3
    c, s = np.cos(th), np.sin(th)
    expected = {
        "rx": [[1, 0, 0], [0, c, -s], [0, s, c]],
        "ry": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "rz": [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }[axis]
    rv = torch.zeros(3, dtype=torch.float64)
    rv[axis_index(axis) - 3] = th
    assert torch.equal(g.rotvec_to_matrix(rv), torch.tensor(expected, dtype=torch.float64))


def test_compose_is_lemma_1(rng):
    a1 = torch.tensor(rng.normal(size=(50, 6)) * 0.3)
    a2 = torch.tensor(rng.normal(size=(50, 6)) * 0.3)
    c = g.compose(a1, a2)
    R1, R2 = (Rotation.from_rotvec(a[:, 3:].numpy()) for a in (a1, a2))
    np.testing.assert_allclose((R1 * R2).as_matrix(), g.rotvec_to_matrix(c[:, 3:]).numpy(), atol=1e-12)
    t = np.einsum("bij,bj->bi", R1.as_matrix(), a2[:, :3].numpy()) + a1[:, :3].numpy()
    np.testing.assert_allclose(c[:, :3].numpy(), t, atol=1e-12)


@pytest.mark.parametrize("axis", AXES)
def test_compose_along_one_axis_is_addition(axis, rng):
    a1, a2 = torch.zeros(20, 6, dtype=torch.float64), torch.zeros(20, 6, dtype=torch.float64)
    a1[:, axis_index(axis)] = torch.tensor(rng.uniform(-0.5, 0.5, 20))
    a2[:, axis_index(axis)] = torch.tensor(rng.uniform(-0.5, 0.5, 20))
    torch.testing.assert_close(g.compose(a1, a2), a1 + a2, atol=1e-12, rtol=0)


def test_pose_motion_round_trip(rng):
    pose = g.motion_to_matrix(torch.tensor(rng.normal(size=6)))
    motion = torch.tensor(rng.normal(size=6) * 0.2)
    moved = pose @ g.motion_to_matrix(motion)  # the camera moved by ``motion`` in its own frame
    torch.testing.assert_close(g.matrix_to_motion(torch.linalg.inv(pose) @ moved), motion, atol=1e-12, rtol=0)
    torch.testing.assert_close(g.motion_to_matrix(g.matrix_to_motion(pose)), pose, atol=1e-12, rtol=0)


def test_unknown_axis_is_named():
    with pytest.raises(ValueError, match="'tw'.*tx, ty, tz, rx, ry, rz"):
        axis_index("tw")


def test_each_axis_has_one_unit_and_unknown_axes_are_refused():
    from mrcert.core.axes import is_translation, unit

    assert [unit(a) for a in ("tx", "ty", "tz", "rx", "ry", "rz")] == ["m"] * 3 + ["rad"] * 3
    assert is_translation("tz") and not is_translation("rz")
    with pytest.raises(ValueError, match="unknown motion axis 'yaw'"):
        unit("yaw")
