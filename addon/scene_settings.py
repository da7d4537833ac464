"""Temporary changes to Blender settings, always put back.

Work that renders with its own settings (a dataset capture, a whole-scene
frame) records each change here and restores the originals when it ends, also
on errors and cancellation, so the user's scene is never left altered.
"""

from __future__ import annotations


class TemporarySettings:
    """Records ``setattr`` changes and undoes them with ``restore`` (idempotent)."""

    def __init__(self):
        self._saved: list = []  # (owner, attribute, original value), in the order they were set

    def keep(self, owner, attr: str) -> None:
        """Remember ``owner.attr`` as it is now, to be restored even if something else changes it."""
        if not any(o == owner and a == attr for o, a, _ in self._saved):  # the first original counts
            self._saved.append((owner, attr, getattr(owner, attr)))

    def set(self, owner, attr: str, value) -> None:
        """Set ``owner.attr = value``, remembering the original (a no-op when already equal)."""
        if getattr(owner, attr) != value:
            self.keep(owner, attr)
            setattr(owner, attr, value)

    def set_all(self, owner, values: dict) -> None:
        """``set`` each attribute of ``values``, in order (dicts keep insertion order)."""
        for attr, value in values.items():
            self.set(owner, attr, value)

    def restore(self) -> list:
        """Put every original back; returns messages for those that could not be restored."""
        errors = []
        # Forward order: an enum set before another that depends on it (media type before file
        # format, view transform before look) is restored first too.
        for owner, attr, value in self._saved:
            try:
                setattr(owner, attr, value)
            except (AttributeError, TypeError, ValueError, ReferenceError) as exc:
                errors.append(f"{attr}: {exc}")
        self._saved.clear()
        return errors

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.restore()
