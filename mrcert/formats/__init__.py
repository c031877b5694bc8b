"""The verification community's formats: ONNX classifiers (:mod:`.onnx_model`) and VNN-LIB
properties (:mod:`.vnnlib`), read for ``task=verify`` and written for ``task=export``."""
