"""Infrastructure: configs and their validation, run identity, the MLflow store and runs,
checkpoints, input checks, the device. Imports ``mrcert.core`` and ``mrcert.errors``."""
