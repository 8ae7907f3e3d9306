"""Write the example's two STL files: the default hook's surface (the deformable part) and the
default rounded plug at its start pose (the rigid part), both in mm.

Provenance: jsnap's own generators (the canonical cantilever of the default scene meshed at
0.8 mm, its boundary triangles; the preset plug's tessellated rounded box). Run from this folder:

    python make_files.py
"""

from pathlib import Path

import trimesh

import jsnap
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.presets import default_rigid
from jsnap._geometry.scene import connector_geometry

here = Path(__file__).parent
scene = jsnap.load_scene()
geom = connector_geometry(scene)
mesh = mesh_cantilever(geom, 0.8)
trimesh.Trimesh(mesh.points, mesh.boundary_faces()).export(here / "hook.stl")
plug = default_rigid("cantilever", scene["connector"], scene["plug"])
surface = plug.mesh()
surface.apply_translation(plug.start)
surface.export(here / "plug.stl")
print(f"wrote {here / 'hook.stl'} and {here / 'plug.stl'}")
