"""Reporting: per-image logs and their metrics, table cells from runs, the paper's tables, figures
and numbers, the evidence page. Imports ``mrcert.infra``, ``mrcert.core`` and the task registry."""
