"""``.ci/system-deps`` (run by ``make install`` and CI) decides which system libraries are present."""

import os
import subprocess
from pathlib import Path

from tests.conftest import ROOT

SCRIPT = ROOT / ".ci" / "system-deps"


def fake_tools(folder: Path, libraries: list[str]) -> dict[str, str]:
    """An environment whose ``ldconfig -p`` lists ``libraries`` first and then a long cache (as
    on a real system), and whose user is not root and has no sudo: nothing can be installed."""
    folder.mkdir()
    listing = "".join(f"\t{lib} (libc6,x86-64) => /usr/lib/{lib}\n" for lib in libraries)
    (folder / "cache.txt").write_text(listing + "\tlibfiller.so.1 (libc6,x86-64) => /usr/lib/libfiller.so.1\n" * 20000)
    tools = {"ldconfig": f"cat {folder / 'cache.txt'}", "id": "echo 1000", "sudo": "exit 1"}
    for name, body in tools.items():
        (folder / name).write_text(f"#!/bin/sh\n{body}\n")
        (folder / name).chmod(0o755)
    return os.environ | {"PATH": f"{folder}:{os.environ['PATH']}"}


def test_present_libraries_are_never_reported_missing(tmp_path):
    env = fake_tools(tmp_path / "bin", ["libusb-1.0.so.0", "libgomp.so.1"])
    for _ in range(20):  # the old pipe raced: a present library looked missing in some runs
        proc = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0 and proc.stderr == "", proc.stderr


def test_a_missing_library_is_named_with_the_command_that_installs_it(tmp_path):
    env = fake_tools(tmp_path / "bin", ["libusb-1.0.so.0"])
    proc = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip() == (
        "mrcert needs the system libraries libgomp1: run 'sudo apt-get install libgomp1' (Debian/Ubuntu)"
    )
