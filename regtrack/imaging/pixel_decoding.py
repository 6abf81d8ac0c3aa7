"""Checks before DICOM pixel data are decoded, and the advice when decoding fails.

pydicom decodes compressed pixel data through plug-ins (pylibjpeg with its libjpeg,
openjpeg and rle back-ends, Pillow, GDCM, pyjpegls; see
https://pydicom.github.io/pydicom/stable/guides/plugin_table.html).  Two failures used to
end in the same wrong advice, "install pylibjpeg", with pylibjpeg installed (issue 53):

* a header claiming 65535 x 65535 pixels: pydicom tries to allocate 8.6 GB, or reports a
  byte-count mismatch; :func:`check_pixel_header` refuses the size from the header alone,
  before any decoding;
* a 12-bit JPEG Extended image: Pillow does not decode 12-bit JPEG and pylibjpeg-libjpeg
  refuses some encoders' streams, while GDCM (not installed) would decode it.
  :func:`decode_failure` asks pydicom which plug-ins are installed for the transfer syntax,
  quotes what each installed one said, and names only the ones really missing, with the
  PyPI package to install.
"""

from __future__ import annotations

from typing import Any

#: More pixels than any mammography detector or scanned film (the largest full-field
#: detectors are about 4,000 x 5,600 pixels; a 50 micron film scan of 24 x 30 cm is
#: 4,800 x 6,000); 2**28 pixels is 0.5 GB at 16 bits.
MAX_PIXELS = 2**28

#: pydicom plug-in name -> what to ``pip install`` for it.
PYPI_PACKAGE = {
    "gdcm": "python-gdcm",
    "pylibjpeg": "pylibjpeg pylibjpeg-libjpeg pylibjpeg-openjpeg pylibjpeg-rle",
    "pyjpegls": "pyjpegls",
    "pillow": "pillow",
}


def _int(ds: Any, keyword: str, default: int | None = None) -> int | None:
    try:
        value = ds.get(keyword, default)
        return None if value is None else int(value)
    except (TypeError, ValueError):
        return None


def check_pixel_header(ds: Any, name: str) -> str | None:
    """A one-line problem with the pixel-data size the header claims, or None.

    Refuses ``Rows x Columns x NumberOfFrames x SamplesPerPixel`` above
    :data:`MAX_PIXELS`, and, for uncompressed transfer syntaxes, a ``PixelData`` shorter
    than ``Rows x Columns x frames x samples x BitsAllocated / 8`` bytes.
    """
    rows, cols = _int(ds, "Rows"), _int(ds, "Columns")
    if rows is None or cols is None or rows <= 0 or cols <= 0:
        return None  # the reader names missing Rows/Columns in its own words
    frames = _int(ds, "NumberOfFrames", 1) or 1
    samples = _int(ds, "SamplesPerPixel", 1) or 1
    bits = _int(ds, "BitsAllocated", 16) or 16
    n = rows * cols * frames * samples
    if n > MAX_PIXELS:
        return (f"{name}: cannot decode the pixel data: Rows x Columns {rows} x {cols}"
                + (f" x {frames} frames" if frames > 1 else "")
                + f" ({n:.2g} pixels, {n * bits / 8 / 2**30:.1f} GiB) is larger than any "
                "mammogram; the header is corrupt: fix Rows/Columns or export the image again")
    ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    try:
        compressed = bool(getattr(ts, "is_compressed", False))
    except ValueError:  # a UID that is no transfer syntax
        return (f"{name}: cannot decode the pixel data: TransferSyntaxUID {ts} (0002,0010) is "
                "not a transfer syntax; the file meta information is corrupt: export the "
                "image again")
    if not compressed and "PixelData" in ds:
        try:
            have = len(ds.PixelData)
        except Exception:  # noqa: BLE001 - an unreadable element: pydicom reports it
            return None
        need = n * bits // 8
        if have < need:
            return (f"{name}: cannot decode the pixel data: PixelData holds {have} bytes but "
                    f"Rows x Columns x BitsAllocated ({rows} x {cols} x {bits}"
                    + (f" x {frames} frames" if frames > 1 else "")
                    + f") need {need}; the file is truncated or those tags are wrong")
    return None


def _plugin_errors(err: BaseException) -> dict[str, str]:
    """``{plugin: its message}`` from pydicom's "exceptions were raised by all available
    plugins" error (one ``  name: message`` line per plug-in)."""
    out: dict[str, str] = {}
    for line in str(err).splitlines()[1:]:
        head, sep, msg = line.strip().partition(": ")
        if sep and head and " " not in head:
            out[head] = " ".join(msg.split())[:160]
    return out


def decode_failure(ds: Any, name: str, err: BaseException) -> str:
    """One line saying why the pixel data could not be decoded and what would help.

    For a compressed transfer syntax it names the installed plug-ins and what each said,
    and the plug-ins that are *not* installed with their PyPI packages; it never advises
    installing what is already there.
    """
    ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    tsn = getattr(ts, "name", str(ts))
    bits = _int(ds, "BitsStored")
    what = f"transfer syntax {tsn}" + (f", {bits}-bit" if bits else "")
    first = " ".join((str(err).strip().splitlines() or [type(err).__name__])[0].split())[:200]
    if ts is None or not getattr(ts, "is_compressed", False):
        return (f"{name}: cannot decode the pixel data ({what}): {first}; the pixel data do not "
                "match the header (Rows, Columns, BitsAllocated, SamplesPerPixel): the file is "
                "truncated or those tags are wrong")
    try:
        from pydicom.pixels import get_decoder

        decoder = get_decoder(ts)
        installed = list(decoder.available_plugins)
        missing = [m.split(" - ")[0].strip() for m in decoder.missing_dependencies]
    except Exception:  # noqa: BLE001 - no pydicom decoder at all for this syntax
        return (f"{name}: cannot decode the pixel data ({what}): {first}; pydicom has no "
                "decoder for this transfer syntax: re-export the image uncompressed")
    said = _plugin_errors(err)
    parts = [f"{name}: cannot decode the pixel data ({what})"]
    if installed:
        tried = "; ".join(f"{p}: {said[p]}" for p in installed if p in said)
        parts.append(f"the installed decoders ({', '.join(installed)}) failed"
                     + (f" ({tried})" if tried else f" ({first})"))
    if missing:
        pkgs = ", ".join(f"{m} (pip install {PYPI_PACKAGE.get(m, m)})" for m in missing)
        parts.append(("not installed: " if installed else "no decoder for it is installed: ")
                     + f"{pkgs}; install one of them or re-export the image uncompressed")
    else:
        parts.append("every decoder pydicom knows for it is installed: the data are corrupt "
                     "or use an unsupported variant; re-export the image uncompressed")
    return ": ".join(parts[:2]) + ("; " + "; ".join(parts[2:]) if len(parts) > 2 else "")
