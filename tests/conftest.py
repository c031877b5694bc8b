import os

import numpy as np
import pytest
import torch

os.environ.setdefault("MLFLOW_ENABLE_ASYNC_LOGGING", "false")

# The paper's 160 x 90 camera (SPEC section 2).
PAPER_K = torch.tensor([[386.274, 0.0, 80.0], [0.0, 386.274, 45.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def random_cloud(rng: np.random.Generator, n: int = 20000, behind: int = 500) -> tuple[torch.Tensor, torch.Tensor]:
    """Points mostly inside the paper camera's view (some behind it), random colours."""
    front = np.column_stack([rng.uniform(-1.6, 1.6, n), rng.uniform(-0.9, 0.9, n), rng.uniform(0.8, 4.0, n)])
    back = np.column_stack([rng.uniform(-1, 1, behind), rng.uniform(-1, 1, behind), rng.uniform(-2.0, 0.0, behind)])
    pts = np.concatenate([front, back])
    return torch.from_numpy(pts), torch.from_numpy(rng.uniform(0, 1, (len(pts), 3)).astype(np.float32))


def random_motions(rng: np.random.Generator, per_axis: int = 3) -> torch.Tensor:
    """A few motions on each single axis (paper-sized ranges) plus combined ones."""
    scale = np.array([0.05, 0.05, 0.1, 0.0436, 0.0436, 0.122])
    rows = []
    for axis in range(6):
        for _ in range(per_axis):
            m = np.zeros(6)
            m[axis] = rng.uniform(-2, 2) * scale[axis]
            rows.append(m)
    rows += list(rng.uniform(-1, 1, (per_axis, 6)) * scale)
    return torch.tensor(np.array(rows))
