"""Reading a stationary focus stack: its images from image files (:func:`read_image_stack`)
or a Zarr array (:func:`read_zarr_stack`), its focus positions from a text file
(:func:`read_focus_positions`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["read_focus_positions", "read_image_stack", "read_zarr_stack"]


def read_image_stack(paths: Sequence[str | Path], *, grey: bool = False,
                     on_image: Callable[[int], None] | None = None) -> np.ndarray:
    """Read grey images (TIFF, PNG, ...) into an (N, H, W) stack, in the order given, each
    turned as its orientation tag says; ``grey`` converts colour images to luma
    (:func:`sffscan.stages.fields.image_io.read_image`); ``on_image``, where given, is called
    with the number of images read after each (a progress display's hook).

    Raises
    ------
    ValueError
        If a file cannot be read, is colour without ``grey``, or differs in shape or dtype
        from the first (the message names the file).
    """
    from sffscan.stages.fields.image_io import read_image

    if len(paths) < 3:
        raise ValueError(f"a focus stack needs at least 3 images, got {len(paths)}")
    images: list[np.ndarray] = []
    for p in paths:
        img = read_image(p, grey=grey)
        if images and (img.shape != images[0].shape or img.dtype != images[0].dtype):
            raise ValueError(f"{p}: shape {img.shape} {img.dtype} differs from the first image's "
                             f"{images[0].shape} {images[0].dtype}")
        images.append(img)
        if on_image is not None:
            on_image(len(images))
    return np.stack(images)


def read_zarr_stack(path: str | Path, *, array: str | None = None
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an (N, H, W) focus stack from a Zarr array (or an array inside a Zarr group).

    Returns the stack and the array's ``focus_heights_um`` attribute (None if it has none).
    """
    import zarr

    node: Any = zarr.open(str(path), mode="r")
    if isinstance(node, zarr.Group):
        if array is None:
            names = [k for k, v in node.members() if isinstance(v, zarr.Array)]
            raise ValueError(f"{path}: is a Zarr group; name its stack array with --array "
                             f"(arrays: {', '.join(names) or 'none'})")
        node = node.get(array)
        if not isinstance(node, zarr.Array):
            raise ValueError(f"{path}: has no array '{array}'")
    stack = np.asarray(node[...])
    if stack.ndim != 3:
        raise ValueError(f"{path}: stack array must be (N, H, W), got shape {stack.shape}")
    attr = node.attrs.get("focus_heights_um")
    return stack, (None if attr is None else np.asarray(attr, dtype=np.float64))


def read_focus_positions(path: str | Path, *, scale_to_um: float = 1.0) -> np.ndarray:
    """Focus positions from a text file: numbers separated by newlines, commas or spaces.

    Lines starting with ``#`` are comments. ``scale_to_um`` converts the file's unit to µm
    (1000 for mm, 1e6 for m).
    """
    text = Path(path).read_text(encoding="utf-8")
    values: list[float] = []
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0]
        for token in line.replace(",", " ").split():
            try:
                values.append(float(token) * scale_to_um)
            except ValueError:
                raise ValueError(f"{path}:{n}: not a number: {token!r}") from None
    if not values:
        raise ValueError(f"{path}: no focus positions found")
    return np.asarray(values, dtype=np.float64)
