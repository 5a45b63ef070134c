"""open3d is optional: the package imports, and works short of registration and decimation,
where it cannot be imported."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

# A None entry in sys.modules makes every later `import open3d` raise ImportError.
_WITHOUT_OPEN3D = "import sys\nsys.modules['open3d'] = None\n"


def _run_without_open3d(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _WITHOUT_OPEN3D + textwrap.dedent(code)],
        cwd=cwd, capture_output=True, text=True, timeout=300,
    )


def test_modules_import_without_open3d(tmp_path):
    code = """
        import importlib, pkgutil
        import reconstruct.cli.main, reconstruct.compare, reconstruct.mesh.ops, reconstruct.pipeline
        for package in (reconstruct.compare, reconstruct.pipeline):
            for module in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
                importlib.import_module(module.name)
        assert sys.modules["open3d"] is None
    """
    result = _run_without_open3d(code, tmp_path)
    assert result.returncode == 0, result.stderr


def test_solids_and_text_clouds_work_without_open3d(tmp_path):
    code = """
        import numpy as np
        from reconstruct.compare import load_geometry, write_distance_ply
        from reconstruct.mesh.ops import solid, write_stl

        height = np.fromfunction(lambda r, c: np.sin(r / 3) + c / 10, (12, 15))
        write_stl("solid.stl", solid(height, 1.0, pixel_size=0.5))
        np.savetxt("cloud.xyz", np.random.default_rng(0).uniform(size=(50, 3)))
        cloud = load_geometry("cloud.xyz", units="cm")
        write_distance_ply("cloud.ply", cloud.points, None, cloud.points[:, 2], 1.0)
    """
    result = _run_without_open3d(code, tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "solid.stl").stat().st_size > 84
    assert (tmp_path / "cloud.ply").stat().st_size > 50 * 19
