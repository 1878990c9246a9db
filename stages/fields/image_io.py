"""Reading the images of a focus stack: file order, orientation and colour.

- **Order.** A shell glob sorts ``image_1 image_10 image_11 ... image_2``: the focus order
  would be wrong without a word. :func:`natural_order` sorts names by their text and the
  value of their numbers (``image_2`` before ``image_10``) and says when the order is
  ambiguous: two names that only differ by zero padding or case, names that do not share
  one pattern, more than one number that changes from name to name, or no number at all.
- **Orientation.** A camera or an editor may store the pixels as taken and an orientation
  tag (TIFF/EXIF tag 274) saying how to show them. :func:`read_image` reads the pixels
  unchanged (tifffile for TIFF, OpenCV for the rest, every bit depth kept) and applies the
  tag (:func:`apply_orientation`, the eight EXIF cases as Pillow's ``exif_transpose``).
- **Colour.** A focus stack is grey. A colour image is refused (naming the file) unless
  ``grey=True``, which converts it to luma with OpenCV's ``cvtColor`` (ITU-R BT.601:
  Y = 0.299 R + 0.587 G + 0.114 B, same dtype, alpha ignored).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

__all__ = ["ORIENTATION_TAG", "apply_orientation", "natural_key", "natural_order",
           "read_image", "read_orientation"]

ORIENTATION_TAG = 274  # TIFF / EXIF "Orientation"
_TIFF = (".tif", ".tiff")
_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key of a file name: text parts case-folded, digit runs by their value."""
    return tuple((1, int(part)) if i % 2 else (0, part.casefold())
                 for i, part in enumerate(_DIGITS.split(name)))


def natural_order(paths: Sequence[str | Path]) -> tuple[list[Path], str | None]:
    """``paths`` sorted naturally by file name, and why the order is ambiguous (or None).

    Returns
    -------
    sorted : list of Path
    ambiguous : str or None
        A sentence naming the names concerned when the order cannot be trusted.
    """
    items = [Path(p) for p in paths]
    ordered = sorted(items, key=lambda p: (natural_key(p.name), str(p)))
    names = [p.name for p in ordered]
    keys = [natural_key(n) for n in names]
    for a, b, ka, kb in zip(names, names[1:], keys, keys[1:], strict=False):
        if ka == kb:
            return ordered, (f"'{a}' and '{b}' differ only by zero padding or case, so their "
                             "order is not defined by their names")
    parts = [_DIGITS.split(n) for n in names]
    if all(len(p) == 1 for p in parts):
        return ordered, "the names carry no number: sorted alphabetically"
    skeletons = {tuple(p[::2]) for p in parts}
    if len(skeletons) > 1:
        shown = sorted("#".join(s) for s in skeletons)[:3]
        return ordered, ("the names do not share one pattern (" + ", ".join(shown)
                         + "; # = a number), so a natural sort may interleave them")
    numbers = [p[1::2] for p in parts]
    varying = [i for i in range(len(numbers[0])) if len({int(n[i]) for n in numbers}) > 1]
    if len(varying) > 1:
        return ordered, (f"{len(varying)} numbers change from name to name ('{names[0]}' .. "
                         f"'{names[-1]}'); sorted by the first, then the next")
    return ordered, None


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_RAW_EXIF = b"Raw profile type exif\x00"


def _png_exif(path: Path) -> bytes | None:
    """The data of a PNG file's eXIf chunk (b"" when it has none), read by walking the
    chunks' headers; None when the file is not a well-formed PNG (Pillow then reads it).

    Pillow's ``getexif`` decodes a PNG's whole image to find an eXIf chunk that may follow
    the image data: that doubled the cost of reading a PNG stack (a 640 x 512 16-bit frame:
    4.7 ms for the tag, 4.9 ms for the pixels with OpenCV).
    """
    try:
        with open(path, "rb") as f:
            return _png_chunks_exif(f)
    except OSError:
        return None  # as before: Pillow's path says what it can


def _png_chunks_exif(f: BinaryIO) -> bytes | None:
    """:func:`_png_exif` of an open file."""
    if f.read(8) != _PNG_SIGNATURE:
        return None
    while True:
        head = f.read(8)
        if len(head) < 8:
            return None  # no IEND: truncated
        length, kind = int.from_bytes(head[:4], "big"), head[4:]
        if kind == b"eXIf":
            data = f.read(length)
            return data if len(data) == length else None
        if kind == b"IEND":
            return b""
        if kind in (b"tEXt", b"zTXt", b"iTXt"):  # ImageMagick's EXIF: Pillow reads it
            if f.read(min(length, len(_RAW_EXIF))) == _RAW_EXIF:
                return None
            f.seek(-min(length, len(_RAW_EXIF)), 1)
        f.seek(length + 4, 1)  # the data and its CRC


def read_orientation(path: str | Path) -> int:
    """The orientation tag (1..8) of an image file; 1 (as stored) when it has none."""
    p = Path(path)
    value: object = 1
    if p.suffix.lower() in _TIFF:
        import tifffile

        with tifffile.TiffFile(p) as tif:
            tag = tif.pages[0].tags.get(ORIENTATION_TAG)  # type: ignore[union-attr]
            value = 1 if tag is None else tag.value
    elif (exif := _png_exif(p)) is not None:  # a PNG: its chunks read, not its pixels
        if exif:
            from PIL import Image

            tags = Image.Exif()
            tags.load(b"Exif\x00\x00" + exif)  # as Pillow's PNG reader passes it
            value = tags.get(ORIENTATION_TAG, 1)
    else:
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(p) as im:
                value = im.getexif().get(ORIENTATION_TAG, 1)
        except (UnidentifiedImageError, OSError):
            value = 1  # a format Pillow does not know carries no tag it could read
    try:
        k = int(value)  # type: ignore[call-overload]
    except (TypeError, ValueError):
        return 1
    return k if 1 <= k <= 8 else 1


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """The image as it is meant to be shown, for an EXIF/TIFF orientation 1..8.

    (H, W) or (H, W, C) in; the same dtype out, (W, H, ...) for 5..8. The cases are those
    of Pillow's ``ImageOps.exif_transpose``: 2 mirror left-right, 3 rotate 180°, 4 mirror
    top-bottom, 5 transpose, 6 rotate 90° clockwise, 7 transverse, 8 rotate 90°
    counter-clockwise.
    """
    a = np.asarray(image)
    if orientation == 2:
        a = a[:, ::-1]
    elif orientation == 3:
        a = a[::-1, ::-1]
    elif orientation == 4:
        a = a[::-1]
    elif orientation == 5:
        a = np.swapaxes(a, 0, 1)
    elif orientation == 6:
        a = np.rot90(a, k=-1)
    elif orientation == 7:
        a = np.swapaxes(a, 0, 1)[::-1, ::-1]
    elif orientation == 8:
        a = np.rot90(a, k=1)
    return np.ascontiguousarray(a)


def read_image(path: str | Path, *, grey: bool = False) -> np.ndarray:
    """One image of a stack, oriented as its tag says, (H, W) grey in its own dtype.

    Parameters
    ----------
    path : path-like
        TIFF (read with tifffile), PNG, JPEG, ... (read with OpenCV).
    grey : bool, keyword-only
        Convert a colour image (3 or 4 channels) to luma, ITU-R BT.601 (OpenCV
        ``cvtColor``); without it a colour image is refused.

    Raises
    ------
    ValueError
        The file cannot be read, is colour without ``grey``, or has another channel count
        (the message names the file).
    """
    p = Path(path)
    rgb = p.suffix.lower() in _TIFF  # tifffile gives RGB(A), OpenCV BGR(A)
    img: np.ndarray
    if rgb:
        import tifffile

        try:
            img = tifffile.imread(p)
        except (OSError, ValueError, tifffile.TiffFileError) as err:
            raise ValueError(f"{p}: cannot read as a TIFF image ({err})") from None
        if img.ndim == 3 and img.shape[0] in (3, 4) and img.shape[-1] not in (3, 4):
            img = np.moveaxis(img, 0, -1)  # planar (C, H, W) storage
    else:
        read = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)  # no orientation applied, any depth
        if read is None:
            raise ValueError(f"{p}: cannot read as an image")
        img = np.asarray(read)
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    if img.ndim == 3 and img.shape[-1] in (3, 4):
        if not grey:
            raise ValueError(f"{p}: colour image ({img.shape[-1]} channels); a focus stack is "
                             "grey: add --grey to convert it to luma (ITU-R BT.601)")
        codes = {(True, 3): cv2.COLOR_RGB2GRAY, (True, 4): cv2.COLOR_RGBA2GRAY,
                 (False, 3): cv2.COLOR_BGR2GRAY, (False, 4): cv2.COLOR_BGRA2GRAY}
        if img.dtype not in (np.uint8, np.uint16, np.float32):
            raise ValueError(f"{p}: colour image of dtype {img.dtype}: only uint8, uint16 or "
                             "float32 colour images can be converted to grey")
        img = cv2.cvtColor(np.ascontiguousarray(img), codes[(rgb, img.shape[-1])])
    if img.ndim != 2:
        raise ValueError(f"{p}: expected a grey image (or colour with --grey), got shape "
                         f"{img.shape}")
    return apply_orientation(img, read_orientation(p))
