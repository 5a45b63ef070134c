"""ptm-reconstruct: reflectance photographs of an object to a PTM, normals, heights and a mesh.

Subpackages, lowest first (each imports only those before it, and :mod:`ptmcore`):

* :mod:`reconstruct.calibration` — the pinhole camera model, light directions and positions
  from glossy spheres, light-layout checks;
* :mod:`reconstruct.mesh` — grid meshes from height maps, PLY/OBJ/GLB/STL, decimation;
* :mod:`reconstruct.surface` — normal integration, flattening, segmentation, accuracy;
* :mod:`reconstruct.report` — raster outputs, figures, report.html, the web viewer export;
* :mod:`reconstruct.compare` — a laser scan against a reconstruction;
* :mod:`reconstruct.viewer` — the preview window and relighting;
* :mod:`reconstruct.pipeline` — the run, stage by stage; :mod:`reconstruct.cli` — the command.

The names below are the run's public stages (``docs/tutorial.md``), loaded on first use so that
``import reconstruct.mesh`` (say) does not import the whole pipeline.
"""

__all__ = [
    "Capture",
    "CompareOptions",
    "RunOptions",
    "RunResult",
    "estimate_normals",
    "fit_relighting",
    "integrate_surface",
    "load_capture",
    "make_mesh",
    "resolve_mask",
    "run",
    "run_capture",
    "run_compare",
    "write_surface_files",
]


def __getattr__(name: str):
    if name in __all__:
        import reconstruct.pipeline

        return getattr(reconstruct.pipeline, name)
    raise AttributeError(f"module 'reconstruct' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
