"""Write clip.msh and pin.stl: a C-shaped pipe clip on a base block and a rigid pin, in mm.

Provenance: gmsh's OpenCASCADE kernel with this script (gmsh 4.15), ``python make_files.py``
from this folder. The C (inner radius 2.0, outer 2.9, its mouth 3.3 wide at the inner radius)
lies in the x-y plane on a base block whose bottom face is the physical group "fixed", and is
extruded 4 mm along z (P1 tetrahedra, element size 0.8). The pin, a cylinder of radius 1.9
along z (trimesh, 96 sections), starts 0.3 mm above the mouth's edges and is pushed along -y:
it spreads each arm by 0.25 mm.
"""

import math

import gmsh
import trimesh

R_IN, R_OUT, WIDTH, MOUTH, SIZE = 2.0, 2.9, 4.0, 3.3, 0.8
PIN = 1.9

gmsh.initialize()
gmsh.option.setNumber("General.Terminal", 0)
occ = gmsh.model.occ
ring, _ = occ.cut([(2, occ.addDisk(0, 0, 0, R_OUT, R_OUT))], [(2, occ.addDisk(0, 0, 0, R_IN, R_IN))])
# The mouth: a wedge from the centre, its edges MOUTH apart at the inner radius.
half = math.asin(MOUTH / 2 / R_IN)
tip = [occ.addPoint(10 * math.sin(s * half), 10 * math.cos(s * half), 0) for s in (-1, 1)]
corners = [occ.addPoint(0, 0, 0), *tip]
lines = [occ.addLine(corners[i], corners[(i + 1) % 3]) for i in range(3)]
c, _ = occ.cut(ring, [(2, occ.addPlaneSurface([occ.addCurveLoop(lines)]))])
base_y = -R_OUT - 1.2
shape, _ = occ.fuse(c, [(2, occ.addRectangle(-3.5, base_y, 0, 7.0, 1.5))])
occ.extrude(shape, 0, 0, WIDTH)
occ.synchronize()
bottom = [t for _, t in gmsh.model.getEntities(2) if abs(occ.getCenterOfMass(2, t)[1] - base_y) < 1e-6]
gmsh.model.addPhysicalGroup(3, [t for _, t in gmsh.model.getEntities(3)], name="clip")
gmsh.model.addPhysicalGroup(2, bottom, name="fixed")
gmsh.option.setNumber("Mesh.MeshSizeMax", SIZE)
gmsh.option.setNumber("Mesh.MeshSizeMin", SIZE / 3)
gmsh.model.mesh.generate(3)
gmsh.write("clip.msh")
gmsh.finalize()

pin = trimesh.creation.cylinder(radius=PIN, height=8.0, sections=96)
pin.apply_translation([0, R_IN * math.cos(half) + PIN + 0.3, WIDTH / 2])
pin.export("pin.stl")
print("wrote clip.msh and pin.stl")
