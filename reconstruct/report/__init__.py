"""What a run shows a person: the raster outputs (normal maps, albedo, height), the figures and
charts, the summary in words and the self-contained ``report.html``, the OpenLIME web-viewer export, the
mesh picture drawn in software (raster) and the off-screen pyvista renders of a comparison (rendering;
pyvista is imported only when one is made).
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "figures": ["Previews", "previews", "stack_thumbnail"],
        "html": ["contact_sheet_picks", "report_html", "write_report_html"],
        "outputs": ["albedo_texture", "albedo_to_srgb8", "normals_to_rgb16", "write_height_tiff", "write_json", "write_normals_png",
                    "write_npy"],
        "raster": ["render_mesh"],
        "rendering": ["plotter", "render_image"],
        "web": ["export_openlime", "export_relightable", "lrgb_planes"],
    },
)
