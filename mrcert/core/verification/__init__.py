"""Deterministic verification, shared by ``method=bound_propagation``, ``method=enumeration`` and
``task=verify``: bounds through a network (:mod:`.network`), bounds on the images of a pose
interval (:mod:`.image_bounds`), a box of inputs verified or falsified by splitting
(:mod:`.boxes`), and the images of a one-axis pose interval enumerated exactly (:mod:`.events`)."""
