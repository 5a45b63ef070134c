"""Package boundaries promised in the README."""

import subprocess
import sys


def test_ptmcore_imports_without_3d_libraries():
    code = (
        "import sys, ptmcore, ptmcore.images, ptmcore.fit, ptmcore.normals, ptmcore.lp\n"
        "heavy = {'open3d', 'pyvista', 'vtk', 'trimesh', 'skimage'} & set(sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
