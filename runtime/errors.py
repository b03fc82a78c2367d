"""Exceptions the runtime raises for problems a user can fix (as opposed to bugs)."""

from __future__ import annotations


class ModelError(Exception):
    """A model folder or file is missing, unreadable, or not a valid dadiff model.

    The message is one line naming the file and, where it applies, the metadata key.
    """


class InputError(ValueError):
    """A caller-supplied value is unusable: init box, frame, preset, override, provider, threads."""
