"""Reference simulators: the systems of docs/systems.md turned into trajectory files.

This package knows physics and nothing of learning.  Typical use::

    from data_gen import load_scene, generate
    traj = generate(load_scene("lorenz3"))          # an mpnode.data.Trajectories
"""
from .initial import closed_loop_start, initial_states, trajectory_rng  # noqa: F401
from .scenes import BUILTIN, SETS, Scene, SceneSet, load_scene, read_scene  # noqa: F401
from .simulate import generate, integrate, simulate  # noqa: F401
from .systems import SYSTEMS, make_rhs  # noqa: F401
