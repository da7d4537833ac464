"""A stand-in for ``bpy.types.UILayout`` that records what a panel draws (bpy has no window here)."""

from types import SimpleNamespace


class RecordingLayout:
    """``row``/``column``/``box`` nest; ``label``, ``prop`` and ``operator`` append to ``log``;
    ``operator`` returns a namespace that collects the properties the panel sets."""

    def __init__(self, log):
        self.log, self.enabled = log, True

    def row(self, **kw):
        return RecordingLayout(self.log)

    column = box = row

    def label(self, text="", **kw):
        self.log.append(("label", text))

    def prop(self, data, name, **kw):
        getattr(data, name)  # the property must exist
        self.log.append(("prop", name))

    def operator(self, idname, **kw):
        props = SimpleNamespace()
        self.log.append(("operator", idname, props))
        return props
