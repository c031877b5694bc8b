"""The tasks: one module per task (``render``, ``train``, ``certify``, ``smooth``, ``attack``,
``tables``, ``import``), each a ``run(cfg, ctx)`` function, plus what they share (``evaluation``,
``inputs``). Their table -- names, identities, logs -- is :mod:`mrcert.infra.tasks`. This layer may
import every other one; nothing imports it but the entry point (``mrcert.__main__``)."""
