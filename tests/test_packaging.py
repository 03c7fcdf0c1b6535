"""The sdist is the source as a clone has it (MANIFEST.in): its tests run from it, so every
committed file they read must be in it (helper-199: weights/lineage.yaml and docs/img/ were not,
and nine tests failed from an unpacked sdist)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NOT_IN_SDIST = {".gitignore"}  # committed, and rightly left out


def test_manifest_takes_every_committed_file(monkeypatch):
    try:
        tracked = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("no git checkout here (an unpacked sdist)")
    # setuptools reads MANIFEST.in the way the build does (a Python 3.11 venv has it; 3.12's may not)
    FileList = pytest.importorskip("setuptools.command.egg_info", reason="setuptools not installed").FileList

    monkeypatch.chdir(REPO)
    files = FileList()
    files.findall()
    for line in (REPO / "MANIFEST.in").read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            files.process_template_line(line)
    # setuptools adds the package, pyproject.toml and MANIFEST.in itself
    taken = {Path(f).as_posix() for f in files.files} | {"pyproject.toml", "MANIFEST.in"}
    left = sorted(f for f in tracked.splitlines()
                  if f not in taken and f not in NOT_IN_SDIST and not f.startswith("psctl/"))
    assert not left, f"committed but not in the sdist (MANIFEST.in): {left}"
