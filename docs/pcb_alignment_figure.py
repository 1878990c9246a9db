"""Figure: ``sffscan stack --grey`` on the focus-stack-pcb stack, without and with ``--align``.

Reads the two height maps saved with ``--save-npy`` and the all-in-focus textures of the two
mosaics, writes ``docs/pcb-alignment.png``. Usage (from the repository root)::

    python docs/pcb_alignment_figure.py NOALIGN.zarr ALIGN.zarr [-o docs/pcb-alignment.png]
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import zarr  # noqa: E402


def _read(path: str, name: str) -> np.ndarray:
    return np.asarray(zarr.open_group(path, mode="r")[name][...], dtype=np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("noalign")
    ap.add_argument("align")
    ap.add_argument("-o", "--output", default="docs/pcb-alignment.png")
    a = ap.parse_args()
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.2), constrained_layout=True)
    for col, (path, title) in enumerate(((a.noalign, "without --align"),
                                         (a.align, "with --align"))):
        h = _read(path, "height")
        t = _read(path, "texture")
        im = axes[0, col].imshow(h, cmap="viridis", vmin=0, vmax=9, interpolation="antialiased")
        axes[0, col].set_title(f"height (frame index), {title}")
        axes[1, col].imshow(t, cmap="gray", interpolation="antialiased")
        axes[1, col].set_title(f"all-in-focus image, {title}")
        for ax in axes[:, col]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.colorbar(im, ax=axes[0, :], shrink=0.8, label="focus position (frame)")
    fig.suptitle("focus-stack-pcb (P. Aimonen, MIT licence): 10 frames, magnification +1.5 % "
                 "per frame\nwhite: not covered by every aligned frame (left invalid)",
                 fontsize=11)
    fig.savefig(a.output, dpi=64)
    print(f"wrote {a.output}")


if __name__ == "__main__":
    main()
