"""The numbers the paper reports (CoRL 2022; docs/method.md §5), shown beside ours with
``tables.show_paper=true``. Keys: (axis, arch, variant) -> values; MetaRoom, 120 test images.
"""

from __future__ import annotations

AXES_ORDER = ("tz", "tx", "ty", "rz", "rx", "ry")

# The paper's MetaRoom experiment: its data set, training poses per class and test images.
DATASET = "MetaRoom"
TRAIN_POSES = 500
TEST_IMAGES = 120

# Table 3: smoothed models' benign accuracy, 5-perturbed empirical robust accuracy, certified accuracy.
_T3 = {  # axis: [(benign, 5-pert, certified) for V-R18, A-R18, V-R50, A-R50]
    "tz": [(0.858, 0.817, 0.792), (0.842, 0.833, 0.817), (0.675, 0.617, 0.558), (0.867, 0.850, 0.817)],
    "tx": [(0.825, 0.783, 0.700), (0.900, 0.875, 0.833), (0.767, 0.675, 0.508), (0.867, 0.825, 0.708)],
    "ty": [(0.850, 0.825, 0.767), (0.892, 0.875, 0.817), (0.792, 0.767, 0.683), (0.942, 0.925, 0.892)],
    "rz": [(0.817, 0.742, 0.608), (0.958, 0.933, 0.883), (0.758, 0.717, 0.633), (0.950, 0.917, 0.883)],
    "rx": [(0.842, 0.800, 0.633), (0.950, 0.942, 0.867), (0.767, 0.742, 0.567), (0.942, 0.933, 0.867)],
    "ry": [(0.892, 0.875, 0.708), (0.925, 0.925, 0.917), (0.808, 0.783, 0.717), (0.992, 0.992, 0.967)],
}
_ORDER = [("resnet18", "vanilla"), ("resnet18", "augmented"), ("resnet50", "vanilla"), ("resnet50", "augmented")]

SMOOTHED_PERTURBED_5 = {(a, *m): vals[i][1] for a, vals in _T3.items() for i, m in enumerate(_ORDER)}
CERTIFIED = {(a, *m): vals[i][2] for a, vals in _T3.items() for i, m in enumerate(_ORDER)}
SMOOTHED_BENIGN = {(a, *m): vals[i][0] for a, vals in _T3.items() for i, m in enumerate(_ORDER)}

# Table 1 (augmented) and its appendix twin (vanilla): base benign, base / smoothed 100-perturbed.
_T1 = {  # axis: {(arch, variant): (base benign, base 100-pert, smoothed 100-pert)}
    "tz": {
        ("resnet18", "augmented"): (0.858, 0.758, 0.817),
        ("resnet50", "augmented"): (0.875, 0.775, 0.825),
        ("resnet18", "vanilla"): (0.800, 0.708, 0.783),
        ("resnet50", "vanilla"): (0.708, 0.517, 0.567),
    },
    "tx": {
        ("resnet18", "augmented"): (0.925, 0.785, 0.867),
        ("resnet50", "augmented"): (0.883, 0.633, 0.800),
        ("resnet18", "vanilla"): (0.817, 0.608, 0.758),
        ("resnet50", "vanilla"): (0.717, 0.467, 0.617),
    },
    "ty": {
        ("resnet18", "augmented"): (0.925, 0.808, 0.842),
        ("resnet50", "augmented"): (0.917, 0.842, 0.908),
        ("resnet18", "vanilla"): (0.825, 0.675, 0.792),
        ("resnet50", "vanilla"): (0.817, 0.674, 0.758),
    },
    "rz": {
        ("resnet18", "augmented"): (0.933, 0.875, 0.892),
        ("resnet50", "augmented"): (0.933, 0.867, 0.917),
        ("resnet18", "vanilla"): (0.800, 0.667, 0.717),
        ("resnet50", "vanilla"): (0.783, 0.558, 0.675),
    },
    "rx": {
        ("resnet18", "augmented"): (0.975, 0.908, 0.892),
        ("resnet50", "augmented"): (0.925, 0.850, 0.917),
        ("resnet18", "vanilla"): (0.867, 0.667, 0.750),
        ("resnet50", "vanilla"): (0.767, 0.467, 0.692),
    },
    "ry": {
        ("resnet18", "augmented"): (0.917, 0.867, 0.925),
        ("resnet50", "augmented"): (0.975, 0.933, 0.983),
        ("resnet18", "vanilla"): (0.917, 0.692, 0.808),
        ("resnet50", "vanilla"): (0.800, 0.600, 0.742),
    },
}
BASE_BENIGN = {(a, *m): v[0] for a, d in _T1.items() for m, v in d.items()}
BASE_PERTURBED_100 = {(a, *m): v[1] for a, d in _T1.items() for m, v in d.items()}
SMOOTHED_PERTURBED_100 = {(a, *m): v[2] for a, d in _T1.items() for m, v in d.items()}


def base_benign_range(arch: str) -> tuple[float, float]:
    """The lowest and highest test accuracy of the paper's base models of ``arch`` (Table 1 and
    its appendix twin): what "performs normally on the test set" means in the paper."""
    values = [v for (_, a, _), v in BASE_BENIGN.items() if a == arch]
    return min(values), max(values)


# Real robot (tabletop): benign accuracy (one value for both) and 10-perturbed, base / smoothed.
TABLETOP_BENIGN = 0.833
TABLETOP_PERTURBED_10 = {  # axis: (base, smoothed)
    "tx": (0.763, 0.789),
    "ty": (0.781, 0.816),
    "tz": (0.798, 0.825),
    "rx": (0.771, 0.772),
    "ry": (0.746, 0.754),
    "rz": (0.825, 0.833),
}

# Pixel-wise smoothing (Hu et al., AISTATS 2024), as its authors' released logs report it:
# (axis, half-width of the interval, method, model, pixel sigma, frames, certified accuracy).
PIXELWISE_REPORTED = (
    ("tz", 0.01, "pixel-wise smoothing", "resnet50", 0.5, 7000, 0.225),
    ("tz", 0.01, "pixel-wise smoothing", "resnet50", 0.5, 2000, 0.192),
    ("tz", 0.01, "motion smoothing", "resnet50", None, None, 0.50),
)
