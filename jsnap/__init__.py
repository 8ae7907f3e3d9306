"""jsnap: real-time, batched, differentiable simulation of robotic snap-fit connection.

Units everywhere: mm, N, MPa, s, tonne (density in t/mm^3).
"""

import jax

# The build is done in float64 (assembly, factorisations, reduction); rollouts cast to the
# dtype they are asked for (float32 by default). Without x64 JAX would silently demote the
# build to float32.
jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
