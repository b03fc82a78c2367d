"""The scene generator's one error type, shared by its modules (scenes, night, photos, library scenes)."""

from __future__ import annotations

from ..errors import DadiffError


class SceneError(DadiffError, ValueError):
    """Bad generator input or a missing photo source (one-line message)."""
