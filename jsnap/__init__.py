"""jsnap: real-time, batched, differentiable simulation of robotic snap-fit connection.

Units everywhere: mm, N, MPa, s, tonne (density in t/mm^3).

    import jsnap
    scene = jsnap.load_scene()            # the shipped default scene
    model = jsnap.build(scene)            # host: mesh, assembly, contact samples
    result = jsnap.rollout(model)         # pure JAX: jit, vmap, grad
    result.insertion_force                # (steps,) N
    jax.grad(loss)(params)                # through contact (docs/differentiation.md)
    jsnap.identify(model, "measured.csv") # fit E, friction, damping to a measured force
"""

from jsnap._apps import xla as _xla

# XLA compiles the contact solvers' small loops into one kernel each (1.4-1.7x faster reduced steps); set
# before JAX starts its CPU backend, unless the user's XLA_FLAGS say otherwise (jsnap._apps.xla).
_xla.configure()

import jax  # noqa: E402

# The build is done in float64 (assembly, factorisations); rollouts cast to the dtype they
# are asked for (float32 by default). Without x64 JAX would silently demote the build.
jax.config.update("jax_enable_x64", True)

from jsnap._apps.identify import FitResult, Measurement, MeasurementError, identify, load_measurement  # noqa: E402
from jsnap._build.model import Model, Params, build  # noqa: E402
from jsnap._geometry.scene import Scene, SceneError, load_scene  # noqa: E402
from jsnap._core.step import Prepared, Result, State, init_state, prepare, rollout, step  # noqa: E402

__version__ = "0.1.0"
__all__ = [
    "FitResult",
    "Measurement",
    "MeasurementError",
    "Model",
    "Params",
    "Prepared",
    "Result",
    "Scene",
    "SceneError",
    "State",
    "build",
    "identify",
    "init_state",
    "load_measurement",
    "load_scene",
    "prepare",
    "rollout",
    "step",
]
