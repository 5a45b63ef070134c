"""Looking at a result: the pyvista preview window (live relighting, view modes, measuring and
profiles and their export, clean figures, the light disk and scale bar in overlays.py, the
keys in keys.py), the scene it shows, RTIViewer's specular enhancement and a relief shading
(shading.py), and ``reconstruct relight``'s renderings
of a PTM or HSH file under any light (RTIViewer's modes).
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "preview": ["PreviewWindow", "build_plotter", "has_display", "render_screenshot"],
        "relighting": ["load_source", "render", "renders", "sweep_lights", "write_gif", "write_image"],
        "scene": ["PreviewScene", "Style", "load_scene", "mode_colors", "profile", "relit_texture"],
        "shading": ["relief_shading"],
        "measurements": ["profile_figure", "write_distance_csv", "write_profile_csv"],
    },
)
