import os

# Offscreen rendering everywhere in the tests (MuJoCo and pyvista), as the Makefile sets it.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def pytest_collection_modifyitems(config, items):
    """The files holding slow tests first (each file's own order kept): under `make test`'s
    `-n auto --dist loadfile` a long file then starts at once and short ones fill the end,
    instead of one worker starting a long file as the other runs out of work."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)
