"""Drive a modal operator's ``modal`` without a window (bpy has none here).

``TIMER``, ``MOVE`` (viewport navigation), ``KEY`` (other input) and ``ESC``
are the events; :class:`OperatorState` stands in for the operator instance.
"""

from __future__ import annotations

import types
from types import SimpleNamespace

TIMER, MOVE, KEY, ESC = (SimpleNamespace(type=t, value=v) for t, v in
                         [("TIMER", "NOTHING"), ("MOUSEMOVE", "NOTHING"), ("A", "PRESS"), ("ESC", "PRESS")])


class OperatorState:
    """An operator's instance state: its session, no timer or area, ``report``
    recording into ``reports``, ``attrs`` as instance attributes, and every
    other attribute of ``cls`` read through (methods bound to this object), so
    ``cls.modal(state, context, event)`` runs the operator's own code."""

    def __init__(self, cls, session, **attrs):
        self._cls = cls
        self._session, self._timer, self._area, self.reports = session, None, None, []
        self.__dict__.update(attrs)

    def __getattr__(self, name):
        value = getattr(self._cls, name)
        return types.MethodType(value, self) if isinstance(value, types.FunctionType) else value

    def report(self, level, message):
        self.reports.append((set(level), message))
