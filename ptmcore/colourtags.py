"""sRGB colour tags for the images written for people to look at, through Pillow.

Every image a person is meant to look at (albedo, textures, report figures, thumbnails,
renderings) says that it is sRGB, so that colour-managed viewers (browsers, Photoshop, macOS
Preview, ImageJ) show it as intended. The project's own PNG writer tags with ``srgb=True``
(:mod:`ptmcore.png`); an image that Pillow or matplotlib writes gets the keyword arguments of
:func:`srgb_save_options` (Pillow's ``Image.save``, matplotlib's ``savefig(pil_kwargs=...)``):

* PNG: the ``sRGB`` chunk (rendering intent 0, perceptual) with the ``gAMA`` and ``cHRM`` chunks
  the PNG specification recommends beside it (:data:`ptmcore.png.SRGB_CHUNKS`).
* JPEG, TIFF, WebP: the sRGB ICC profile of :func:`srgb_icc_profile` (a JPEG's APP2
  ``ICC_PROFILE`` segment, TIFF tag 34675), which Pillow embeds.
* GIF and the rest: nothing. GIF has no ICC profile in practice (GIF89a's ``ICCRGBG1``
  application extension is read by almost no viewer and written by no library used here);
  browsers show an untagged image as sRGB anyway.

Data (16-bit normal maps, masks, height TIFFs, the web page's coefficient planes) is written
untagged: a tag claims that the values are colours, which invites colour-managed programs to
convert them.
"""

from __future__ import annotations

import functools

from .png import SRGB_CHUNKS

__all__ = ["ICC_FORMATS", "srgb_icc_profile", "srgb_save_options"]

#: Pillow formats that embed an ICC profile given as ``icc_profile``.
ICC_FORMATS = frozenset({"JPEG", "TIFF", "WEBP", "JPEG2000", "AVIF", "HEIF"})

# The profile header's creation date (ICC.1 7.2.8: bytes 24-35, six big-endian 16-bit numbers),
# fixed so that the same image gives the same bytes on every run: littlecms stamps the time.
_PROFILE_DATE = (2000, 1, 1, 0, 0, 0)


@functools.cache
def srgb_icc_profile() -> bytes:
    """The bytes of an sRGB ICC profile (littlecms' built-in sRGB, 588 bytes), made once.

    Its creation date is fixed (:data:`_PROFILE_DATE`) so that files embedding it are the
    same from run to run; the profile ID stays zero ("not computed"), which ICC allows.
    """
    try:
        from PIL import ImageCms

        profile = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    except ImportError:  # pragma: no cover - a Pillow built without littlecms
        import imagecodecs

        profile = imagecodecs.cms_profile("srgb")
    date = b"".join(v.to_bytes(2, "big") for v in _PROFILE_DATE)
    return profile[:24] + date + profile[36:]


def srgb_save_options(fmt: str) -> dict:
    """Keyword arguments for Pillow's ``Image.save(..., format=fmt)`` (or matplotlib's
    ``savefig(..., pil_kwargs=...)``) that tag the image as sRGB: the sRGB chunks for
    ``"PNG"``, the sRGB ICC profile for the formats of :data:`ICC_FORMATS`, nothing for the
    others (GIF, BMP, ...). A new dictionary on every call (matplotlib keeps the one it gets)."""
    fmt = fmt.upper()
    if fmt == "PNG":
        from PIL.PngImagePlugin import PngInfo

        info = PngInfo()
        for kind, data in SRGB_CHUNKS:
            info.add(kind, data)
        return {"pnginfo": info}
    if fmt in ICC_FORMATS:
        return {"icc_profile": srgb_icc_profile()}
    return {}
