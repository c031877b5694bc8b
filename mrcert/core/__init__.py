"""The maths: camera motions, the exact projection, motion smoothing and its statistics, the
base classifiers. Imports nothing from mrcert but ``mrcert.errors`` and itself."""
