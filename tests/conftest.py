"""Shared fixtures: meshes and assemblies are built once per session (JAX compiles are slow)."""

import os

import numpy as np
import pytest

import jsnap  # noqa: F401  (enables float64)
from jsnap._build import fem as _fem
from jsnap._geometry.cantilever import mesh_box
from jsnap._core.pmi import SparseBlocks

# The CLI tests call `main` in this process: keep its JAX compilation cache (a setting of the whole
# process, see jsnap._build.cache.use_compilation_cache) from reaching every test after them.
os.environ.setdefault("JSNAP_XLA_CACHE", "0")

# The straight reference arm of refs/calculix-cantilever (tests/data/README.md).
ARM = dict(L=10.0, h=1.2, b=4.0)


def free_blocks(asm):
    f = asm.free
    return SparseBlocks.from_scipy(*(m[f][:, f] for m in (asm.K_lam, asm.K_mu, asm.M1)))


@pytest.fixture(scope="session")
def small_arm():
    """A coarse P1 arm (270 free dofs) with its static tip-load deflection."""
    asm = _fem.assemble(mesh_box(ARM["h"], ARM["b"], ARM["L"], 1.2), "P1")
    f = _fem.traction_load(asm, lambda x: np.isclose(x[2], ARM["L"]), [1.0, 0.0, 0.0])
    u = _fem.solve_static(asm, 2200.0, 0.35, f)
    return asm, free_blocks(asm), f, u


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A fresh jsnap cache folder (``JSNAP_CACHE``) for the module's builds."""
    with pytest.MonkeyPatch.context() as mp:
        path = tmp_path_factory.mktemp("jsnap_cache")
        mp.setenv("JSNAP_CACHE", str(path))
        yield path
