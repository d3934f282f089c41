"""The add-on's core: pure Python and numpy (no bpy, no torch); ``addon/blender`` is its glue."""


def release() -> None:
    """Free what this process keeps from one render or edit to the next: the networks' thread pools, the loaded
    model sets (their sessions and the encodings they keep), this session's calibrations, measured reference lobes
    and refinements, and the meshes' ray-tracing structures. What is on disk stays. The add-on's unregister calls
    it: a disabled add-on kept all of it (2 idle threads and tens of MB more at each disable and enable)."""
    from . import quality
    from .neural import calibrate, models, refine, session
    from .render import integrator

    session.shutdown_pools()
    models.clear_cache()
    calibrate.clear_cache()
    refine.clear_memory()
    quality.clear_memo()
    integrator.clear_tracers()
