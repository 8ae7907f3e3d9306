"""The geometry layer's errors (apart, so that every geometry module can raise them)."""

from __future__ import annotations

__all__ = ["SceneError", "SceneWarning"]


class SceneError(ValueError):
    """A scene file or scene value is invalid; the message names the key and the value."""


class SceneWarning(UserWarning):
    """A scene value that is allowed but likely gives a poor result; the message names the key."""
