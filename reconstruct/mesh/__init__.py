"""Meshes: grid meshes from height maps and the files they are delivered in.

:mod:`~reconstruct.mesh.grid` builds a triangle mesh with one vertex per pixel of a height
map; :mod:`~reconstruct.mesh.ply` and :mod:`~reconstruct.mesh.obj` write it as PLY and as OBJ
with its material and texture; :mod:`~reconstruct.mesh.ops` decimates it, closes it into a
watertight solid for printing, and writes GLB and STL.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "grid": ["GridMesh", "grid_mesh"],
        "obj": ["write_obj"],
        "ops": ["decimate", "solid", "write_glb", "write_stl"],
        "ply": ["write_binary_ply", "write_ply"],
        "topology": ["boundary_edges", "directed_edges", "edge_face_counts", "edge_keys"],
    },
)
