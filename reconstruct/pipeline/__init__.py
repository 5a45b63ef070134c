"""The run of a capture, stage by stage: what ``reconstruct run`` and ``compare`` do.

Owns the options (:mod:`.options`), loading a capture (:mod:`.capture`), the stages from
normals to written files (:mod:`.stages`), the typed report (:mod:`.report`), staged output
folders (:mod:`.staging`), stage timing (:mod:`.profiling`), files written in background
threads (:mod:`.writer`), and the runs composing them
(:mod:`.run`, :mod:`.compare_run`). ``docs/tutorial.md`` runs the stages one by one.
"""

import lazy_loader

# Loaded on first use (scikit-image's way): the command line reads the options' choices
# without importing every stage.
__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "capture": ["Capture", "NearLights", "capture_images", "find_lp", "load_capture", "read_mask"],
        "compare_run": ["CompareResult", "run_compare"],
        "options": ["CompareOptions", "RunOptions", "choices", "default"],
        "profiling": ["Stages"],
        "report": ["CompareReport", "RunReport"],
        "run": ["RunResult", "run", "run_capture", "run_normals", "run_ptm"],
        "staging": ["StagedOutput", "staged_output"],
        "stages": ["AUTO_MESH_VERTICES", "NormalsResult", "Relighting", "Surface", "auto_step", "web_export",
                   "estimate_normals", "fit_relighting", "integrate_surface", "leave_one_out",
                   "light_model", "make_mesh", "resolve_mask", "write_height", "write_maps", "write_meshes",
                   "write_surface_files"],
        "writer": ["FileWriter"],
    },
)
