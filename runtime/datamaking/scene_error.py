"""The scene generator's one error type, shared by its modules (scenes, night, photos, library scenes)."""

from __future__ import annotations


class SceneError(ValueError):
    """Bad generator input or a missing photo source (one-line message)."""
