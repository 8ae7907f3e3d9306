"""jsnap: real-time, batched, differentiable simulation of robotic snap-fit connection.

Units everywhere: mm, N, MPa, s, tonne (density in t/mm^3).

    import jsnap
    scene = jsnap.load_scene()            # the shipped default scene
    model = jsnap.build(scene)            # host: mesh, assembly, contact samples, reduction
    result = jsnap.rollout(model)         # pure JAX: jit, vmap, grad
    result.insertion_force                # (steps,) N
    jsnap.rollout_batch(model, params)    # many parameter sets, motions or start poses at once
    jsnap.identify(model, "measured.csv") # fit E, friction, damping to a measured force
    jsnap.peak_strain(model, result)      # peak strain and stress (a rollout with keep_x=True)

Importing jsnap changes no process-wide setting: it computes in 64 bits only inside its own
functions (``jax.enable_x64`` scoped to each call), and XLA's CPU flags are an explicit opt-in
(:func:`configure_xla_cpu`). Only the names below are public; ``jsnap._*`` is private.
"""

from jsnap._apps.xla import configure_xla_cpu
from jsnap._core.model import Model
from jsnap._core.params import Params
from jsnap._core.rollout import Result, SimulationError, rollout, rollout_batch
from jsnap._core.status import Flag
from jsnap._core.step import Prepared, State, init_state, prepare, step
from jsnap._geometry.scene import Scene, SceneError, SceneWarning, load_scene

__version__ = "0.2.0"

# The build layer (scikit-fem, meshio, trimesh, scipy) and the fitting application (optax) load
# on first use, so that the kernels can be imported and run where those libraries are absent.
_LAZY = {
    "build": "jsnap._build.model",
    "BuildError": "jsnap._build.model",
    "identify": "jsnap._apps.identify",
    "FitResult": "jsnap._apps.identify",
    "Measurement": "jsnap._apps.identify",
    "MeasurementError": "jsnap._apps.identify",
    "load_measurement": "jsnap._apps.identify",
    "strain": "jsnap._build.strain",
    "Strain": "jsnap._build.strain",
    "peak_strain": "jsnap._build.strain",
    "PeakStrain": "jsnap._build.strain",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jsnap' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "BuildError",
    "FitResult",
    "Flag",
    "Measurement",
    "MeasurementError",
    "Model",
    "Params",
    "PeakStrain",
    "Prepared",
    "Result",
    "Scene",
    "SceneError",
    "SceneWarning",
    "SimulationError",
    "State",
    "Strain",
    "build",
    "configure_xla_cpu",
    "identify",
    "init_state",
    "load_measurement",
    "load_scene",
    "peak_strain",
    "prepare",
    "rollout",
    "rollout_batch",
    "step",
    "strain",
]
