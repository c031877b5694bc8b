"""The commands a ``make`` target runs, read from the Makefile, for the page to print beside its figures."""

from __future__ import annotations

from pathlib import Path

from mrcert.reporting.paper_tables import REPRODUCTION

MAKEFILE = Path(__file__).resolve().parents[3] / "Makefile"


def make_stage(target: str, profile: str) -> list[str]:
    """The mrcert commands that ``make TARGET`` runs, as the Makefile writes them (continued
    lines joined, comments dropped, ``$(MRCERT)`` as ``mrcert``, ``$(PROFILE)`` as
    ``profile``, ``$(REPRODUCTION)`` as its experiment, the default ``ATTACKS``); the page's
    last stage, the tables, not among them. Empty without the
    Makefile (an installed copy)."""
    if not MAKEFILE.is_file():
        return []
    lines = MAKEFILE.read_text().split("\n")
    start = next((i for i, line in enumerate(lines) if line.startswith(f"{target}:")), None)
    if start is None:
        return []
    commands, current = [], ""
    for line in lines[start + 1 :]:
        if not line.startswith("\t"):
            break
        text = line.strip().split("  #", 1)[0].rstrip()
        current += " " + text.rstrip("\\").strip()
        if not text.endswith("\\"):
            commands.append(current.strip())
            current = ""
    named = {
        "$(MRCERT)": "mrcert",
        "$(PROFILE)": profile,
        "$(REPRODUCTION)": REPRODUCTION.format(profile=profile),
        "$(ATTACK_SETTING)": "",  # ATTACKS=fixed, the default
    }
    shown = []
    for command in commands:
        for variable, value in named.items():
            command = command.replace(variable, value)
        shown.append(command.strip())
    return [c for c in shown if c.startswith("mrcert ")]
