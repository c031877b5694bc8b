"""The tasks: one module per task (``render``, ``train``, ``certify``, ``smooth``, ``attack``,
``verify``, ``export``, ``viewpoints``, ``tables``, ``import``, ``gather``), each holding its
:class:`~mrcert.infra.tasks.Task` subclass, which ``conf/task/<name>.yaml`` names by ``_target_``,
plus what they share (``evaluation``, ``inputs``). This layer may import every other one; nothing
imports it but the entry point (``mrcert.__main__``) and the task registry, by name."""
