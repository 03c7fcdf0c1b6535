"""Input and output: capture folders, images, normal-map encodings, reports."""

from __future__ import annotations

from types import ModuleType


def __getattr__(name: str) -> ModuleType:  # submodules on first use (psctl._submodule)
    from psctl import _submodule

    return _submodule(__name__, name)
