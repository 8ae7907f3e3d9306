"""Shared fixtures: meshes and assemblies are built once per test run (JAX compiles are slow).

jsnap changes no process-wide JAX setting: tests of the public API run as a user's program does,
with JAX's default 32-bit mode. Tests of internal kernels that compute in float64 on their own
use the ``x64`` fixture (``jax.enable_x64`` for the test's duration), as jsnap's public entry
points do internally.
"""

import os

import jax
import numpy as np
import pytest

from jsnap._build import fem as _fem
from jsnap._build.cache import switched_off
from jsnap._build.fem import sparse_blocks
from jsnap._geometry.cantilever import mesh_box

# The CLI tests call `main` in this process: keep its JAX compilation cache (a setting of the whole
# process) from reaching every test after them.
os.environ.setdefault("JSNAP_XLA_CACHE", "0")

# The straight reference arm of the CalculiX comparison (jsnap/data/calculix-cantilever).
ARM = dict(L=10.0, h=1.2, b=4.0)


def energy_balance_error(res):
    """The largest gap, over a rollout, between the deformable part's energy and what the rigid
    part's work left after friction and the normal forces took theirs (``jsnap.Result``), over
    the largest work so far: the midpoint rule's balance, exact without damping."""
    fields = (res.energy, res.work, res.friction_dissipation, res.normal_dissipation)
    E, work, friction, normal = (np.asarray(a, np.float64) for a in fields)
    budget = np.cumsum(work)
    left = budget - np.cumsum(friction + normal)
    return float(np.abs(E - left).max() / np.abs(budget).max())


# The modules with the longest tests, longest first: the suite runs on two workers, one test
# module each at a time (pytest-xdist, --dist loadfile: a module's fixtures are built once), and
# starting the long ones first keeps one worker from finishing long after the other.
_LONGEST_FIRST = (
    "test_bench.py",
    "test_hook_family.py",
    "test_parts_from_files.py",
    "test_presets.py",
    "test_docs.py",
    "test_notebook.py",
)


def pytest_addoption(parser):
    parser.addoption(
        "--xslow",
        action="store_true",
        # Off by default; set, it reads like jsnap's other switches (0, false, no, off: off).
        default=bool(os.environ.get("JSNAP_XSLOW", "").strip()) and not switched_off("JSNAP_XSLOW"),
        help="also run the checks marked xslow (benchmark-sized: minutes each); or JSNAP_XSLOW=1",
    )


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
    if not config.getoption("--xslow"):
        skip = pytest.mark.skip(reason="xslow: a benchmark-sized check; run it with `python -m pytest --xslow`")
        for item in items:
            if "xslow" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module: the suite compiles hundreds, and each
    keeps its machine code mapped; one process holding them all ran out of memory mappings
    (XLA aborted while compiling, deep into the suite)."""
    yield
    jax.clear_caches()


@pytest.fixture(autouse=True)
def _keep_xla_flags():
    """The command line opts its process in to XLA's small-loop option (``XLA_FLAGS``, read by
    JAX once per process); tests that call it in this process must not leave it set for the
    subprocesses of later tests."""
    saved = os.environ.get("XLA_FLAGS")
    yield
    if saved is None:
        os.environ.pop("XLA_FLAGS", None)
    else:
        os.environ["XLA_FLAGS"] = saved


@pytest.fixture
def x64():
    """JAX's 64-bit types for the test's duration."""
    with jax.enable_x64(True):
        yield


def free_blocks(asm):
    f = asm.free
    return sparse_blocks(*(m[f][:, f] for m in (asm.K_lam, asm.K_mu, asm.M1)))


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
