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


# Subpackages of reconstruct, lowest first: each may import only those before it (and ptmcore),
# as docs/architecture.md draws them.
LAYERS = ["calibration", "mesh", "surface", "report", "compare", "viewer", "pipeline", "batch", "cli"]


def _imports(path):
    import ast

    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module


def test_subpackages_import_only_the_layers_below():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    folders = {name: root / "reconstruct" / name for name in LAYERS[:-1]} | {"cli": root / "cli"}
    wrong = []
    for layer, folder in folders.items():
        allowed = set(LAYERS[: LAYERS.index(layer) + 1])
        for path in folder.glob("*.py"):
            for module in _imports(path):
                parts = module.split(".")
                if parts[0] == "reconstruct" and len(parts) > 1 and parts[1] not in allowed:
                    wrong.append(f"{path.relative_to(root)} imports {module}")
    assert not wrong, wrong


def test_ptmcore_never_imports_reconstruct():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    wrong = [f"{p.name}: {m}" for p in (root / "ptmcore").glob("*.py") for m in _imports(p)
             if m.split(".")[0] in ("reconstruct", "open3d", "trimesh", "pyvista", "vtk", "vtkmodules")]
    assert not wrong, wrong
