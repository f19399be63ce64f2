import os

# Offscreen rendering everywhere in the tests (MuJoCo and pyvista), as the Makefile sets it.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
