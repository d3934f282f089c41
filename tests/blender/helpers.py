"""Helpers shared by the Blender tests."""

from __future__ import annotations


class OperatorReport:
    """What an operator call gave: its result set, or the message of the ERROR it reported."""

    def __init__(self, result=None, error=None):
        self.result = result
        self.error = error

    @property
    def finished(self):
        return self.result == {"FINISHED"}


def run_operator(op, *args, **kwargs) -> OperatorReport:
    """Call ``bpy.ops...`` and return the outcome.

    Blender turns an operator's ERROR report into a RuntimeError for Python callers; this
    separates such clean reports from crashes. A Python exception escaping an operator shows as
    "Traceback" in the message; an exception the operator caught but did not expect shows as
    " failed: ExceptionType"; both fail the calling test.
    """
    try:
        return OperatorReport(result=op(*args, **kwargs))
    except RuntimeError as e:
        text = str(e)
        assert "Traceback" not in text, f"{op.idname()} raised an exception:\n{text}"
        assert not any(
            f" failed: {t}" in text for t in ("AttributeError", "TypeError", "KeyError", "IndexError", "NameError")
        ), text
        return OperatorReport(error=text)


def viewport_reports(monkeypatch, context, exports: int = 3, size=(16, 12)) -> list[tuple]:
    """The reports (kind, text) the viewport's Rendered mode makes over ``exports`` exports of ``context``'s scene
    (edits elsewhere, each exporting again), seen through the scene camera."""
    from types import SimpleNamespace

    from addon.blender import engine, scene_export

    monkeypatch.setattr(engine, "_view_camera", lambda context: None)  # the scene camera
    reports = []
    fake = SimpleNamespace(
        _view_info=set(),
        _view_geometry=scene_export.GeometryCache(),
        report=lambda kind, text: reports.append((kind, text)),
    )
    region = SimpleNamespace(region=SimpleNamespace(width=size[0], height=size[1]))
    for _ in range(exports):
        engine.NeuralLayeredRenderEngine._view_scene(fake, region, context.evaluated_depsgraph_get(), [])
    return reports


class DrawnProps:
    """A stand-in for a panel's ``layout`` that records the names of the properties a ``draw`` puts on it
    (``drawn``); every other layout call gives the layout back, as Blender's sub-layouts do."""

    use_property_split = False
    active = True
    enabled = True

    def __init__(self):
        self.drawn: list[str] = []

    def __getattr__(self, name):
        return lambda *a, **k: self

    def prop(self, data, name, **kw):
        self.drawn.append(name)
